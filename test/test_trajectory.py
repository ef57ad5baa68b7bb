"""core.trajectory: the engine's pose, and a pose set at a stamp (robot_localization's set_pose)."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from bevo_ros.core.pose import compose_se2_floats, propagate_covariance_se2_floats
from bevo_ros.core.trajectory import PlanarTrajectory, check_pose

P = (10.0, -4.0, 2.5)  # the pose set
P_COV = np.diag([0.04, 0.09, 0.01])


def _motions(n: int, seed: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    motions = np.column_stack([rng.uniform(0.5, 1.5, n), rng.normal(0, 0.05, n), rng.normal(0.05, 0.05, n)])
    motions[0] = 0.0  # the first frame: no motion, none uncertain (as the engine gives it)
    covs = [np.zeros((3, 3))]
    for _ in range(n - 1):
        a = rng.normal(size=(3, 3)) * 1e-2
        covs.append(a @ a.T)
    return motions, covs


def _compose_from(pose, cov, motions, covs):
    for m, c in zip(motions, covs):
        cov = propagate_covariance_se2_floats(pose[2], cov, m, c)
        pose = compose_se2_floats(pose, m)
    return pose, cov


def _run(traj: PlanarTrajectory, motions, covs, stamps) -> None:
    for t, m, c in zip(stamps, motions, covs):
        traj.add(t, m, c)


def test_without_a_set_pose_it_composes_the_frames_as_before():
    motions, covs = _motions(30)
    traj = PlanarTrajectory()
    _run(traj, motions, covs, np.arange(30) * 0.1)
    pose, cov = _compose_from((0.0, 0.0, 0.0), np.zeros((3, 3)), motions, covs)
    assert traj.pose == pose  # bit for bit: the engine's pinned trajectories rest on it
    np.testing.assert_array_equal(traj.cov, cov)
    assert traj.z == 0.0 and traj.waiting is None


@pytest.mark.parametrize("j", [0, 7, 19])
def test_a_pose_set_at_a_frames_stamp_starts_the_trajectory_there(j):
    motions, covs = _motions(20)
    stamps = 100.0 + np.arange(20) * 0.1
    traj = PlanarTrajectory()
    _run(traj, motions, covs, stamps)
    assert traj.set_pose(P, 1.5, P_COV, stamp=float(stamps[j])) == "at stamp"
    pose, cov = _compose_from(P, P_COV, motions[j + 1:], covs[j + 1:])
    np.testing.assert_allclose(traj.pose, pose, atol=1e-12)
    np.testing.assert_allclose(traj.cov, cov, atol=1e-15)
    assert traj.z == 1.5
    # the frames after go on from there
    traj.add(stamps[-1] + 0.1, motions[5], covs[5])
    np.testing.assert_allclose(traj.pose, compose_se2_floats(pose, motions[5]), atol=1e-12)


def test_a_stamp_between_frames_takes_the_share_of_its_interval_after_it():
    motions, covs = _motions(12)
    stamps = np.arange(12) * 0.1
    traj = PlanarTrajectory()
    _run(traj, motions, covs, stamps)
    s = stamps[4] + 0.025  # a quarter into frame 5's interval: three quarters of its motion follow
    assert traj.set_pose(P, 0.0, P_COV, stamp=float(s)) == "at stamp"
    pose, cov = _compose_from(P, P_COV, [0.75 * motions[5]], [0.75 * covs[5]])
    pose, cov = _compose_from(pose, cov, motions[6:], covs[6:])
    np.testing.assert_allclose(traj.pose, pose, atol=1e-12)
    np.testing.assert_allclose(traj.cov, cov, atol=1e-15)
    # against a pose set at frame 4: the whole of frame 5's motion more
    other = PlanarTrajectory()
    _run(other, motions, covs, stamps)
    other.set_pose(P, 0.0, P_COV, stamp=float(stamps[4]))
    assert math.dist(other.pose[:2], traj.pose[:2]) > 0.1


def test_a_stamp_after_the_latest_frame_waits_for_the_frame_that_reaches_it():
    motions, covs = _motions(10)
    stamps = np.arange(10) * 0.1
    traj = PlanarTrajectory()
    _run(traj, motions, covs, stamps[:6])
    before = traj.pose
    assert traj.set_pose(P, 0.0, P_COV, stamp=0.55) == "waits"
    assert traj.waiting == 0.55 and traj.pose == before  # nothing moves until a frame reaches it
    traj.add(stamps[6], motions[6], covs[6])  # 0.6: half its interval is after the stamp
    assert traj.waiting is None
    pose, cov = _compose_from(P, P_COV, [0.5 * motions[6]], [0.5 * covs[6]])
    np.testing.assert_allclose(traj.pose, pose, atol=1e-12)
    np.testing.assert_allclose(traj.cov, cov, atol=1e-15)


def test_before_the_first_frame_the_first_frame_takes_the_pose():
    motions, covs = _motions(5)
    for stamp in (None, 9.5, 10.0):
        traj = PlanarTrajectory()
        traj.set_pose(P, 0.0, P_COV, stamp=stamp)
        traj.add(10.0, motions[0], covs[0])  # the first frame: no motion
        np.testing.assert_allclose(traj.pose, P, atol=1e-12)
        np.testing.assert_allclose(traj.cov, P_COV, atol=1e-15)
        traj.add(10.1, motions[1], covs[1])
        np.testing.assert_allclose(traj.pose, compose_se2_floats(P, motions[1]), atol=1e-12)
    traj = PlanarTrajectory()
    traj.set_pose(P, 0.0, P_COV, stamp=10.05)  # after the first frame: set between it and the second
    traj.add(10.0, motions[0], covs[0])
    assert traj.pose == (0.0, 0.0, 0.0) and traj.waiting == 10.05
    traj.add(10.1, motions[1], covs[1])
    np.testing.assert_allclose(traj.pose, compose_se2_floats(P, 0.5 * motions[1]), atol=1e-12)


def test_a_stamp_before_the_frames_kept_is_set_at_the_oldest_and_reset_forgets_all():
    motions, covs = _motions(20)
    stamps = np.arange(20) * 0.1
    traj = PlanarTrajectory(memory=5)
    _run(traj, motions, covs, stamps)
    assert traj.set_pose(P, 0.0, P_COV, stamp=0.3) == "oldest"  # frames 15-19 kept
    pose, _ = _compose_from(P, P_COV, motions[16:], covs[16:])
    np.testing.assert_allclose(traj.pose, pose, atol=1e-12)
    traj.set_pose(P, 2.0, P_COV, stamp=99.0)
    traj.reset()
    assert traj.waiting is None and traj.pose == (0.0, 0.0, 0.0) and traj.z == 0.0
    traj.add(100.0, motions[0], covs[0])
    assert traj.pose == (0.0, 0.0, 0.0)


def test_a_pose_set_replaces_one_that_waits():
    motions, covs = _motions(4)
    traj = PlanarTrajectory()
    _run(traj, motions, covs, [0.0, 0.1])
    traj.set_pose(P, 0.0, P_COV, stamp=5.0)
    traj.set_pose((1.0, 2.0, 0.0), 0.0, np.zeros((3, 3)))  # now: the waiting one is dropped
    assert traj.waiting is None and traj.pose == (1.0, 2.0, 0.0)
    traj.add(5.0, motions[2], covs[2])
    np.testing.assert_allclose(traj.pose, compose_se2_floats((1.0, 2.0, 0.0), motions[2]), atol=1e-12)


def test_check_pose_refuses_what_is_no_pose():
    pose, z, cov = check_pose(1.0, 2.0, 3.5, 0.5, None)
    assert pose == (1.0, 2.0, pytest.approx(3.5 - 2 * math.pi)) and z == 0.5 and not cov.any()
    for bad in [dict(x=math.nan), dict(yaw=math.inf), dict(z=math.nan)]:
        args = dict(x=0.0, y=0.0, yaw=0.0, z=0.0, covariance=None) | bad
        with pytest.raises(ValueError, match="finite"):
            check_pose(**args)
    for cov, what in [(np.eye(2), "(3, 3)"), (np.full((3, 3), math.nan), "finite"),
                      (np.array([[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]), "symmetric"),
                      (np.diag([1.0, -0.1, 1.0]), "positive semi-definite")]:
        with pytest.raises(ValueError, match=re.escape(what)):
            check_pose(0.0, 0.0, 0.0, 0.0, cov)
    with pytest.raises(ValueError, match="memory"):
        PlanarTrajectory(memory=0)


