"""The stateful engine (BevoOdometry): ordering rule, online == batched, errors, covariances."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bevo_ros.config import BevoConfig, build_odometry
from bevo_ros.core.odometry import EngineEvent, InvalidInputError, OutOfOrderError
from bevo_ros.io.learned_params import LearnedParams
from bevo_ros.core.phase_correlation import DpcConfig
from bevo_ros.core.sequence import frame_attitudes, run_sequence
from bevo_ros.datasets.rosbag import feed_engine
from bevo_ros.datasets.synthetic import make_drive

# Trust the gyro (the synthetic accelerometer vibrates by 0.3-0.7 m/s^2, i.e. 2-4 deg).
LEARNED = LearnedParams((1e-6, 1e-6), (1e-1, 1e-1))


@pytest.fixture(scope="module")
def drive():
    d = make_drive(seed=5, duration=2.5, bumps=1.0, render="lazy")
    images = np.stack([np.asarray(d.image(i)) for i in range(len(d.frame_stamps))])
    return d, images


def engine(d, mode: str = "paper", **overrides):
    """The engine in ``mode``; these tests pin the paper pipeline (the batched path is its twin),
    test_fused_odometry the fused one."""
    config = BevoConfig()
    config.odometry.mode = mode
    for key, value in overrides.items():
        setattr(config.filter, key, value)
    return build_odometry(config, LEARNED, camera=d.camera)


def feed(odo, d, images, image_first: bool = False):
    """Messages in stamp order; with ``image_first`` an image precedes the IMU sample of its stamp."""
    return feed_engine(odo, d.imu_stamps, d.gyro, d.accel, d.frame_stamps[: len(images)], images.__getitem__,
                       image_first=image_first, trailing=False)


def test_tracks_the_synthetic_drive_and_is_order_independent(drive):
    d, images = drive
    a = feed(engine(d), d, images)
    b = feed(engine(d), d, images, image_first=True)
    assert len(a) == len(b) == len(images)
    assert a[0].first and np.all(a[0].motion == 0) and np.all(a[0].position == 0)
    est = np.array([s.motion for s in a[1:]])
    err_t = np.linalg.norm(est[:, :2] - d.relative_motion[:, :2], axis=1)
    err_y = np.degrees(np.abs(est[:, 2] - d.relative_motion[:, 2]))
    print(f"\nper-frame error: translation mean {err_t.mean() * 100:.2f} cm max {err_t.max() * 100:.2f} cm; "
          f"yaw mean {err_y.mean():.3f} max {err_y.max():.3f} deg")
    # Wiring check, not the accuracy test (that is test_phase_correlation with true attitude): a
    # sign or frame error gives metres and degrees here; raw accelerometer angles give ~1.9 m, 4.4 deg.
    assert err_t.mean() < 0.2 and err_y.mean() < 0.4
    # An image arriving before the IMU of its stamp waits for it: identical results.
    for sa, sb in zip(a, b):
        assert sa.stamp == sb.stamp
        np.testing.assert_allclose(sa.position, sb.position, atol=1e-9)
        np.testing.assert_allclose(sa.rpy, sb.rpy, atol=1e-9)


def _batched(odo, d, images, imu_keep=None, **kwargs):
    T = lambda a: torch.as_tensor(np.asarray(a))  # noqa: E731
    k = slice(None) if imu_keep is None else imu_keep
    with torch.no_grad():
        return run_sequence(odo.dukf, d.camera.to(dtype=torch.float32), odo.spec, DpcConfig(), T(d.imu_stamps[k]),
                            T(d.gyro[k]), T(d.accel[k]), T(d.frame_stamps), T(images),
                            road_tilt_time_constant=odo.road_tilt_time_constant,
                            mounting_attitude=odo.mounting_attitude, **kwargs)


def test_online_equals_batched_sequence(drive):
    """The per-message engine and the batched training path agree (same functions, same IMU rule)."""
    d, images = drive
    steps = feed(engine(d), d, images)
    online = np.array([s.motion for s in steps[1:]])
    res = _batched(engine(d), d, images)
    batched = res.motion.double().numpy()
    diff = np.abs(online - batched).max()
    print(f"\nmax |online - batched| motion difference: {diff:.2e}")
    assert diff < 1e-6  # every stage is batch-size invariant: in practice exactly 0
    pr_online = np.array([s.pitch_roll_road for s in steps])
    assert np.abs(pr_online - res.pitch_roll_road.numpy()).max() < 1e-6


def test_online_equals_batched_across_an_imu_gap(drive):
    """An IMU gap longer than max_imu_gap restarts the DUKF online; the batched path does the same."""
    d, images = drive
    t = d.imu_stamps - d.imu_stamps[0]
    keep = ~((t > 1.0) & (t < 1.8))  # 0.8 s without IMU, frames keep coming
    odo = engine(d)
    steps = feed_engine(odo, d.imu_stamps[keep], d.gyro[keep], d.accel[keep], d.frame_stamps[: len(images)],
                        images.__getitem__, trailing=False)
    assert odo.counters.imu_gaps == 1 and len(steps) == len(images)
    pr_online = np.array([s.pitch_roll_road for s in steps])
    online = np.array([s.motion for s in steps[1:]])
    res = _batched(odo, d, images, keep, max_imu_gap=odo.max_imu_gap)
    no_restart = _batched(odo, d, images, keep)
    diff_pr = np.abs(pr_online - res.pitch_roll_road.numpy()).max()
    diff_motion = np.abs(online - res.motion.double().numpy()).max()
    ignored = np.abs(pr_online - no_restart.pitch_roll_road.numpy()).max()
    print(f"\n[0.8 s IMU gap] online vs batched: attitude {diff_pr:.1e} rad, motion {diff_motion:.1e}; "
          f"batched without the restart: attitude off by {ignored:.1e} rad")
    assert diff_pr < 1e-9 and diff_motion < 1e-6
    assert ignored > 1e-4  # the restart matters: the test can fail


def test_mounting_attitude_only_with_the_road_tilt_lowpass(drive):
    """The low-pass removes every constant, so the mounting is added back; without it the
    gravity-referenced attitude already holds the mounting: adding it would count it twice."""
    d, images = drive
    mount = (0.02, -0.01)
    out = {}
    for tau in (2.0, 0.0):
        for m in ((0.0, 0.0), mount):
            steps = feed(engine(d, road_tilt_time_constant=tau, mounting_pitch=m[0], mounting_roll=m[1]),
                         d, images[:6])
            out[tau, m] = np.array([s.pitch_roll_road for s in steps])
    np.testing.assert_allclose(out[2.0, mount] - out[2.0, (0.0, 0.0)], np.tile(mount, (6, 1)), atol=1e-12)
    np.testing.assert_array_equal(out[0.0, mount], out[0.0, (0.0, 0.0)])
    odo = engine(d, road_tilt_time_constant=0.0, mounting_pitch=mount[0], mounting_roll=mount[1])
    T = torch.as_tensor
    _, road = frame_attitudes(odo.dukf, T(d.imu_stamps), T(d.gyro), T(d.accel), T(d.frame_stamps[:6]), 0.0,
                              mounting_attitude=mount)
    np.testing.assert_allclose(road.detach().numpy(), out[0.0, mount], atol=1e-12)


def test_covariances_are_honest_shapes(drive):
    d, images = drive
    steps = feed(engine(d), d, images)
    last = steps[-1]
    for cov in (last.pose_covariance, last.twist_covariance):
        assert cov.shape == (6, 6)
        np.testing.assert_allclose(cov, cov.T, atol=1e-12)
        assert np.all(np.linalg.eigvalsh(cov) > -1e-12)
    assert last.pose_covariance[2, 2] >= 1e3  # z is held constant: say so
    # The pose covariance grows along the trajectory (dead reckoning).
    assert steps[-1].pose_covariance[0, 0] > steps[2].pose_covariance[0, 0] > 0
    assert 0.0 < last.peak_quality <= 1.0


def test_motion_covariance_includes_the_attitude_errors(drive):
    """On a bumpy drive the forward error is mostly BEV scale from pitch errors (and roll shears the
    BEV into yaw), which the correlation spread cannot see: the engine adds both, so e^2 / var
    stays O(1) on every axis (without them dx came out ~1000x overconfident)."""
    d, images = drive
    steps = feed(engine(d), d, images)
    err = np.array([s.motion for s in steps[1:]]) - d.relative_motion
    ratios = []
    for e, s in zip(err, steps[1:]):
        c, sn = math.cos(s.motion[2]), math.sin(s.motion[2])
        rot = np.array([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]])
        cov = rot.T @ s.twist_covariance[np.ix_([0, 1, 5], [0, 1, 5])] @ rot * s.dt**2  # back to the step
        ratios.append(e**2 / np.diag(cov))
    ratio = np.mean(ratios, axis=0)
    print(f"\nmean e^2 / var (dx, dy, dyaw) on the bumpy drive: {ratio.round(2)} (1 = consistent)")
    assert np.all(ratio < 20) and np.all(ratio > 0.05)


def test_bad_input_raises_clear_errors(drive):
    d, images = drive
    odo = engine(d)
    odo.add_imu(float(d.imu_stamps[0]), d.gyro[0], d.accel[0])
    with pytest.raises(OutOfOrderError, match="IMU stamp"):
        odo.add_imu(float(d.imu_stamps[0]), d.gyro[1], d.accel[1])
    with pytest.raises(ValueError, match="NaN"):
        odo.add_imu(float(d.imu_stamps[1]), [math.nan, 0, 0], d.accel[1])
    with pytest.raises(ValueError, match="does not match the calibration"):
        odo.add_image(float(d.frame_stamps[0]), images[0][:-2])
    with pytest.raises(ValueError, match="grayscale"):
        odo.add_image(float(d.frame_stamps[0]), np.zeros((2, 2, 3), np.uint8))
    odo.add_image(float(d.frame_stamps[1]), images[1])
    with pytest.raises(OutOfOrderError, match="image stamp"):
        odo.add_image(float(d.frame_stamps[1]), images[1])


def test_images_before_any_imu_are_dropped_and_counted(drive):
    d, images = drive
    odo = engine(d)
    assert odo.add_image(float(d.frame_stamps[0]), images[0], tag="frame 0") == []
    assert odo.pending_tags == ["frame 0"]
    assert odo.flush() == []
    assert odo.counters.dropped_no_imu == 1
    assert odo.take_events() == [EngineEvent("dropped_no_imu", float(d.frame_stamps[0]), "frame 0")]
    assert odo.take_events() == []  # taken once


def test_each_step_carries_its_images_tag_and_drops_are_events(drive):
    """The caller's tag comes back with the step of its image (queued or not); a queue overflow
    reports the dropped image's tag, an IMU gap its stamp."""
    d, images = drive
    odo = engine(d, max_imu_gap=0.05)
    odo.max_pending_images = 1
    t0 = float(d.imu_stamps[0])
    odo.add_imu(t0, d.gyro[0], d.accel[0])
    assert odo.add_image(t0 + 0.01, images[0], tag="a") == []
    assert odo.add_image(t0 + 0.02, images[1], tag="b") == []  # "a" overflows the queue of one
    steps = odo.add_imu(t0 + 1.0, d.gyro[1], d.accel[1])  # releases "b"; a gap > max_imu_gap
    steps += odo.add_image(t0 + 0.5, images[2], tag="c")  # the IMU is past it: processed at once
    assert [s.tag for s in steps] == ["b", "c"]
    assert odo.take_events() == [EngineEvent("dropped_pending_overflow", t0 + 0.01, "a"),
                                 EngineEvent("imu_gaps", t0 + 1.0)]
    assert (odo.counters.dropped_pending_overflow, odo.counters.imu_gaps) == (1, 1)
    assert feed(engine(d), d, images[:2])[0].tag is None  # no tag given


def test_imu_gap_reinitialises_and_reset_restarts(drive):
    d, images = drive
    odo = engine(d, max_imu_gap=0.05)
    odo.add_imu(float(d.imu_stamps[0]), d.gyro[0], d.accel[0])
    odo.add_imu(float(d.imu_stamps[0]) + 1.0, d.gyro[1], d.accel[1])
    assert odo.counters.imu_gaps == 1
    steps = feed(engine(d), d, images)
    odo2 = engine(d)
    feed(odo2, d, images)
    odo2.reset()
    again = feed(odo2, d, images)
    np.testing.assert_allclose(again[-1].position, steps[-1].position, atol=1e-9)


def test_a_frame_whose_bev_is_invalid_is_dropped_not_raised(drive):
    """An absurd attitude (70 deg nose up) leaves no valid BEV pixel: counted drop, no exception,
    no lost state; the engine carries on with the next frames."""
    d, images = drive
    config = BevoConfig()
    config.odometry.mode = "paper"
    odo = build_odometry(config, LearnedParams((1e-6, 1e-6), (1e-3, 1e-3)), camera=d.camera)
    t0 = float(d.imu_stamps[0])
    level, nose_up = [0.0, 0.0, 9.81], [9.81 * math.sin(1.22), 0.0, 9.81 * math.cos(1.22)]
    odo.add_imu(t0, [0.0, 0.0, 0.0], level)
    assert odo.add_image(t0 + 0.05, images[0]) == []  # waits for the IMU after it
    steps = odo.add_imu(t0 + 0.10, [0.0, 0.0, 0.0], nose_up)
    steps += odo.add_image(t0 + 0.10, images[1])
    print(f"\nsteps {len(steps)}, dropped (invalid BEV) {odo.counters.dropped_invalid_bev}")
    assert odo.counters.dropped_invalid_bev >= 1
    assert [e.kind for e in odo.take_events()] == ["dropped_invalid_bev"] * odo.counters.dropped_invalid_bev
    assert odo._last_imu == t0 + 0.10  # the IMU sample was fused, nothing raised
    odo.reset()
    assert len(feed(odo, d, images)) == len(images)  # and the engine works on afterwards


@pytest.mark.parametrize("error", [ValueError, TypeError])
def test_a_bug_while_processing_a_frame_is_raised_not_counted_as_a_drop(drive, monkeypatch, error):
    """Only InvalidBevError is bad input (a drop); any other exception in the frame's processing is
    a bug and must reach the caller."""
    d, images = drive
    odo = engine(d)

    def broken(*args, **kwargs):
        raise error("a bug in the registration")

    monkeypatch.setattr(odo.kernels, "register_prepared", broken)  # the engine's vision functions
    with pytest.raises(error, match="a bug in the registration"):
        feed(odo, d, images[:3])
    assert odo.counters.dropped_invalid_bev == 0


def test_the_invalid_bev_error_is_what_the_engine_counts(drive):
    """The BEV check raises the dedicated error (a ValueError for older callers)."""
    from bevo_ros.core.phase_correlation import InvalidBevError, prepare

    empty = torch.zeros(1, 1, 32, 32)
    with pytest.raises(InvalidBevError):
        prepare(empty, empty, DpcConfig())
    assert issubclass(InvalidBevError, ValueError)


def _relative(a, b) -> np.ndarray:
    """The planar pose of ``b`` (x, y, yaw) in the frame of ``a``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    d = np.asarray(b[:2]) - np.asarray(a[:2])
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], (b[2] - a[2] + math.pi) % (2 * math.pi) - math.pi])


@pytest.mark.parametrize("mode", ["fused", "paper"])
def test_set_pose_moves_the_trajectory_and_nothing_else(drive, mode):
    d, images = drive
    plain = feed(engine(d, mode), d, images)
    odo = engine(d, mode)
    j = 8
    given = (5.0, -3.0, 1.0)
    assert odo.set_pose(*given, z=2.0, covariance=np.diag([0.01, 0.02, 0.003]), stamp=float(d.frame_stamps[j])) == "waits"
    steps = feed(odo, d, images)
    pose = lambda s: (s.position[0], s.position[1], s.rpy[2])  # noqa: E731
    assert len(steps) == len(plain) == len(images)
    for k, (a, b) in enumerate(zip(plain, steps)):
        np.testing.assert_array_equal(a.motion, b.motion)  # the filters are untouched
        np.testing.assert_array_equal(a.rpy[:2], b.rpy[:2])
        if k < j:
            np.testing.assert_array_equal(a.position, b.position)
        else:  # from frame j on: the plain run's motion since frame j, from the pose set
            np.testing.assert_allclose(_relative(given, pose(b)), _relative(pose(plain[j]), pose(a)), atol=1e-9)
            assert b.position[2] == 2.0
    assert steps[j].pose_covariance[0, 0] == pytest.approx(0.01) and steps[j].pose_covariance[5, 5] == pytest.approx(0.003)
    assert steps[-1].pose_covariance[0, 0] > 0.01
    # at a past frame's stamp: the latest pose moves at once; the next frame goes on from there
    assert odo.set_pose(0.0, 0.0, 0.0, stamp=float(d.frame_stamps[2])) == "at stamp"
    # the plain run's motion since frame 2, from the origin
    np.testing.assert_allclose(odo.pose, _relative(pose(plain[2]), pose(plain[-1])), atol=1e-9)
    with pytest.raises(InvalidInputError, match="finite"):
        odo.set_pose(math.nan, 0.0, 0.0)
    with pytest.raises(InvalidInputError, match="semi-definite"):
        odo.set_pose(0.0, 0.0, 0.0, covariance=-np.eye(3))
    odo.reset()
    again = feed(odo, d, images)
    np.testing.assert_array_equal(again[-1].position, plain[-1].position)  # reset forgets the pose set
