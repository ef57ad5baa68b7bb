"""Fused odometry (issue 9): acceleration-aware attitude, gyro yaw, vehicle motion filter, gates.

Synthetic presets run on a half-resolution KITTI-like camera to keep CI fast; the figures the
README quotes come from the same code at full resolution (printed with ``-s``).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from bevo_ros.config import REPO_ROOT, BevoConfig, CameraSettings, build_odometry
from bevo_ros.io.learned_params import LearnedParams, load_learned_params
from bevo_ros.core.geometry import CameraModel
from bevo_ros.datasets.rosbag import feed_engine
from bevo_ros.core.vehicle_dynamics import GRAVITY, compensate_floats, compensate_specific_force
from bevo_ros.core.vehicle_filter import VehicleFilter, VehicleNoise, initial_vehicle_state
from bevo_ros.datasets.synthetic import kitti_like_camera, make_drive, preset_drive
from bevo_ros.evaluation.metrics import motion_scores

FUSED = load_learned_params(REPO_ROOT / "params" / "learned_default.yaml")
# the default with the inertial speed input (fused item 16, and so item 17) switched off
FUSED_NO_INERTIAL = replace(FUSED, vehicle={**FUSED.vehicle, "imu_accel_density": 0.0})
PAPER = load_learned_params(REPO_ROOT / "params" / "learned_paper.yaml")


def small_camera() -> CameraModel:
    return kitti_like_camera(scale=0.5)


def engine(camera, mode: str, learned: LearnedParams | None = None):
    config = BevoConfig()
    config.odometry.mode = mode
    return build_odometry(config, learned or (FUSED if mode == "fused" else PAPER), camera=camera)


def feed(odo, d, images=None):
    """The drive through the engine in the node's order (``datasets.feed_engine``)."""
    return feed_engine(odo, d.imu_stamps, d.gyro, d.accel, d.frame_stamps,
                       (lambda k: images[k]) if images is not None else d.image, trailing=False)


def scores(steps, d) -> dict[str, float]:
    """``evaluation.metrics.motion_scores`` of the drive, and the NEES of the published motions."""
    est = np.array([s.motion for s in steps[1:]])
    gt = d.relative_motion
    road = np.array([s.pitch_roll_road for s in steps])
    # NEES of the published (dx, dy, dyaw) against its covariance (3 = consistent): the step's
    # twist covariance is the motion's, rotated into the frame at t and divided by dt^2.
    nees = []
    for s, g in zip(steps[1:], gt):
        c, s_ = math.cos(s.motion[2]), math.sin(s.motion[2])
        rot = np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]])
        cov = rot.T @ s.twist_covariance[np.ix_([0, 1, 5], [0, 1, 5])] @ rot * s.dt**2
        e = s.motion - g
        nees.append(float(e @ np.linalg.solve(cov, e)))
    return {"nees_mean": float(np.mean(nees)), "nees_median": float(np.median(nees)),
            **motion_scores(est, gt, road, d.pitch_roll_road)}


# ------------------------------------------------------------------------------ pure functions
def test_float_and_tensor_paths_agree():
    """The engine's float arithmetic and the batched tensor form (training) are one computation."""
    rng = np.random.default_rng(0)
    f = VehicleFilter(VehicleNoise())
    sf, st = initial_vehicle_state(), initial_vehicle_state(like=torch.zeros(3, dtype=torch.float64))
    for _ in range(20):
        dt = 0.1
        m = rng.normal(size=(4,)) * [0.05, 0.02, 0.002, 0.002] + [1.2, 0.0, 0.01, 0.0]
        q = float(rng.uniform(0.0, 1.0))
        a = f.step(sf, dt, m[2], forward=m[0], forward_var=1e-3, lateral=m[1], lateral_var=4e-4, rotation=m[3],
                   rotation_var=1e-5, quality=q)
        def T(v):
            return torch.tensor(v, dtype=torch.float64).expand(3)

        b = f.step(st, dt, T(m[2]), forward=T(m[0]), forward_var=T(1e-3), lateral=T(m[1]), lateral_var=T(4e-4),
                   rotation=T(m[3]), rotation_var=T(1e-5), quality=T(q))
        for x, y in zip(a.motion + a.variance, b.motion + b.variance):
            assert float(y[0]) == pytest.approx(x, rel=1e-12, abs=1e-15)
        sf, st = a.state, b.state
    accel, gyro = [0.3, 2.1, 9.7], [0.01, -0.02, 0.15]
    fc, ev = compensate_floats(accel, gyro, 12.0, 0.5, 0.2, 0.3)
    tc, tv = compensate_specific_force(torch.tensor(accel), torch.tensor(gyro), torch.tensor(12.0), torch.tensor(0.5),
                                       torch.tensor(0.2), torch.tensor(0.3))
    assert np.allclose(fc, tc.numpy()) and np.allclose(ev, tv.numpy())
    assert fc[1] == pytest.approx(2.1 - 12.0 * 0.15)  # the centripetal part is gone


def test_gate_rejects_an_outlier_and_carries_the_prediction():
    f = VehicleFilter(VehicleNoise(gate=5.0))
    s = initial_vehicle_state()
    for _ in range(30):  # 12 m/s, steady
        s = f.step(s, 0.1, 0.0, forward=1.2, forward_var=1e-4, lateral=0.0, lateral_var=1e-4, rotation=0.0,
                   rotation_var=1e-6, quality=0.5).state
    out = f.step(s, 0.1, 0.0, forward=19.0, forward_var=1e-4, lateral=3.0, lateral_var=1e-4, rotation=0.0,
                 rotation_var=1e-6, quality=0.5)
    assert not out.accepted[0] and out.mahalanobis[0] > 5
    assert out.motion[0] == pytest.approx(1.2, abs=0.01) and abs(out.motion[1]) < 0.01
    dark = f.step(s, 0.1, 0.0, forward=0.0, forward_var=1e-4, lateral=0.0, lateral_var=1e-4, rotation=0.0,
                  rotation_var=1e-6, quality=0.0)  # textureless: no information, whatever it says
    assert not dark.accepted[0] and dark.motion[0] == pytest.approx(1.2, abs=0.01)


def _bias_after(noise: VehicleNoise, image_turn, gyro_bias: float = 0.0, frames: int = 60, like=None):
    """A steady 12 m/s drive, straight; the gyro's yaw carries ``gyro_bias`` (rad/s) and the images
    read ``image_turn(k)`` (rad) at frame ``k``. -> the bias estimate at the end (rad/s) and how many
    rotations were used (floats, or ``(B,)`` tensors with ``like``)."""
    f, dt = VehicleFilter(noise), 0.1
    s = initial_vehicle_state(like=like)
    used = 0

    def v(x):
        return x if like is None else torch.full_like(like, x)

    for k in range(frames):
        out = f.step(s, dt, v(gyro_bias * dt), forward=v(1.2), forward_var=v(1e-4), lateral=v(0.0), lateral_var=v(1e-4),
                     rotation=v(image_turn(k)), rotation_var=v(noise.image_rotation_std**2), quality=v(0.5))
        s, used = out.state, used + out.accepted[1]
    return s.b, used


def test_an_image_rotation_the_gyro_cannot_have_made_leaves_the_bias_alone():
    """A car ahead turning: for 2 s the images read 1 deg per frame of turn the gyro does not see.
    Inside the Mahalanobis gate (image_rotation_std is 1 deg per frame), so without the rotation
    gate the bias learns a car's turn (-0.55 deg/s, and the heading follows it); with it those
    frames are not the bias's measurement. A real gyro bias of 0.5 deg/s (0.05 deg per frame, well
    inside the gate) is learned as without it, and so is a 5 deg/s one (0.5 deg per frame: the gate
    widens by the bias estimate's 3 sigma while the bias is unknown); an 8 deg/s one is learnt once its
    lasting disagreement has widened the bias's variance, which a car's 3 s turn does not do; the
    float (engine) and tensor (training) paths agree."""
    def car(k):
        return math.radians(1.0) if 20 <= k < 40 else 0.0

    gated, used = _bias_after(VehicleNoise(), car)
    loose, used_loose = _bias_after(VehicleNoise(rotation_gate=math.inf), car)
    print(f"bias after a car's turn: {math.degrees(gated):+.3f} deg/s gated ({used} of 60 used), "
          f"{math.degrees(loose):+.3f} ungated ({used_loose})")
    assert abs(math.degrees(gated)) < 0.02 and used == 40
    assert math.degrees(loose) < -0.2 and used_loose == 60
    for true_bias in (0.5, 5.0):  # deg/s; 5 is 0.5 deg per frame, over the gate but not over its 3 sigma widening
        real, used = _bias_after(VehicleNoise(), lambda k: 0.0, gyro_bias=math.radians(true_bias), frames=300)
        real_loose, _ = _bias_after(VehicleNoise(rotation_gate=math.inf), lambda k: 0.0,
                                    gyro_bias=math.radians(true_bias), frames=300)
        # learnt as without the gate (slowly: half of it in 30 s at image_rotation_std 1 deg)
        assert used == 300 and real == pytest.approx(real_loose, rel=1e-12) and math.degrees(real) > 0.3 * true_bias
    # 8 deg/s is beyond even the widened gate at first: the rejections widen the bias's variance until
    # the images get through (a few seconds), then it is learnt (without that widening: 0 of 300 used)
    real, used = _bias_after(VehicleNoise(), lambda k: 0.0, gyro_bias=math.radians(8.0), frames=300)
    real_loose, _ = _bias_after(VehicleNoise(rotation_gate=math.inf), lambda k: 0.0, gyro_bias=math.radians(8.0),
                                frames=300)
    print(f"an 8 deg/s bias after 30 s: {math.degrees(real):.2f} deg/s ({used} of 300 used), "
          f"{math.degrees(real_loose):.2f} without the gate")
    assert used >= 250 and math.degrees(real) >= math.degrees(real_loose) > 3.0
    def long_car(k):  # 3 s of a car's 1 deg per frame: the widening does not open the gate to it
        return math.radians(1.0) if 20 <= k < 50 else 0.0

    held, used = _bias_after(VehicleNoise(), long_car, frames=80)
    assert abs(math.degrees(held)) < 0.02 and used == 50
    batch, used_t = _bias_after(VehicleNoise(), car, like=torch.zeros(2, dtype=torch.float64))
    assert torch.allclose(batch, torch.full_like(batch, gated), rtol=1e-9, atol=1e-15)
    assert torch.equal(used_t, torch.full((2,), 40))


@pytest.mark.slow
def test_a_car_turning_ahead_does_not_turn_the_heading():
    """Urban preset with traffic, its first 8 s (half-size camera, 10 Hz): the car ahead turns in
    the BEV and the images' rotation reads it (up to 1.6 deg per frame against the road's). With
    the rotation gate the yaw gyro's bias stays put and the heading ends 0.9 deg off, the gyro's
    own +0.8; without it the bias learns the car's turn (-0.51 deg/s) and the heading is 3.9 deg off."""
    cam = small_camera()
    d = preset_drive("urban", seed=1, imu_rate=10, camera=cam, render="lazy", traffic=True, duration=8.0)
    heading, bias = {}, {}
    for gate in (BevoConfig().odometry.rotation_gate, math.inf):
        config = BevoConfig()
        config.odometry.rotation_gate = gate
        odo = build_odometry(config, FUSED, camera=cam)
        est, gt = _clip_motions(odo, d, 0, d.num_frames)
        heading[gate], bias[gate] = math.degrees(est[:, 2].sum() - gt[:, 2].sum()), math.degrees(odo.gyro_bias[2])
    gated, loose = BevoConfig().odometry.rotation_gate, math.inf
    print(f"behind a turning car: heading {heading[gated]:+.2f} deg gated, {heading[loose]:+.2f} ungated; "
          f"yaw gyro bias {bias[gated]:+.3f} / {bias[loose]:+.3f} deg/s")
    assert abs(heading[gated]) < 1.5 and abs(bias[gated]) < 0.08
    assert abs(heading[loose]) > 2.5 and bias[loose] < -0.3


# ------------------------------------------------------------------------------ synthetic presets
@pytest.fixture(scope="module")
def camera():
    return small_camera()


# Limits at half resolution, 100 Hz IMU, short drives (measured: curve 0.12 / 0.18 deg road
# attitude, 2.9 %, 0.024 deg, 1.2 % drift; braking 0.22 / 0.17, 6.9 %, 0.026, 3.6 %; bend_start
# 0.12 / 0.31, 3.3 %, 0.028, 1.2 %; paper mode 13-57 %, yaw 0.28-0.56 deg, 11-29 %). Issue 9 asks
# 0.3 deg, 3 %, 0.05 deg and 1 %: see the README ("How well it does") for what is reached. Braking is the spread one:
# seeds 2-4 of the same 6 s drive give 8.4 / 7.2 / 13.2 % per frame and 4.8 / 2.4 / 6.4 % drift
# (12.2 / 8.4 / 14.0 % and 4.5 / 4.1 / 1.4 % before the pitch-change correction acted through
# accelerations: its drift is the one figure that got worse), so its limits hold seed 1 with a
# margin, not a lucky draw.
PRESET_LIMITS = {  # name: (duration s, road attitude RMS deg, translation %, yaw deg, drift %)
    "curve": (10.0, 0.3, 5.0, 0.04, 3.0),
    "braking": (6.0, 0.45, 9.0, 0.04, 5.0),
    "bend_start": (6.0, 0.45, 5.0, 0.04, 3.0),
}


def test_pitch_change_shifts_the_forward_motion(camera):
    """Two frames projected with pitches that differ by D beyond the truth: the correlation reads
    ``(X^2 + h^2) / h * D`` of extra forward motion (core.motion.pitch_change_shift), whatever the
    common error; removing it gives the motion back."""
    from bevo_ros.core.bev import project_to_bev
    from bevo_ros.core.motion import pitch_change_shift, vehicle_motion_from_registration
    from bevo_ros.core.phase_correlation import prepare, register_prepared

    odo = engine(camera, "fused")
    spec, dpc = odo.spec, odo.dpc
    d = preset_drive("curve", seed=2, duration=1.0, render="lazy", camera=camera, noise=False)
    k = 5
    c = pitch_change_shift(spec, float(camera.T_base_cam[0, 3]), camera.mount_height)

    def forward(common: float, change: float) -> float:
        bevs = []
        for i, extra in ((k - 1, common), (k, common + change)):
            pr = torch.tensor(d.pitch_roll_road[i:i + 1], dtype=torch.float32)
            img = torch.as_tensor(np.asarray(d.image(i)))[None, None]
            bevs.append(prepare(*project_to_bev(img, odo.camera, pr[:, 0] + extra, pr[:, 1], spec), dpc))
        reg = register_prepared(bevs[0], bevs[1], dpc)
        return float(vehicle_motion_from_registration(reg.angle, reg.shift, spec)[0, 0])

    truth = float(d.relative_motion[k - 1, 0])
    D = math.radians(0.2)
    base = forward(0.0, 0.0)
    changed = forward(0.0, D)
    common = forward(math.radians(0.3), 0.0)  # a common error only scales (2 X d / h: 7 % here)...
    both = forward(math.radians(0.3), D)  # ... and the change adds the same shift on top
    print(f"\ntrue dx {truth:.4f} m; read {base:.4f}, with a {math.degrees(D):.1f} deg change {changed:.4f} "
          f"(+{changed - base:.4f}, predicted +{c * D:.4f}); a common 0.3 deg error {common:.4f}, and the change "
          f"on top {both:.4f} (+{both - common:.4f})")
    assert base == pytest.approx(truth, abs=0.01)
    assert changed - base == pytest.approx(c * D, rel=0.25)
    assert both - common == pytest.approx(changed - base, rel=0.1)
    assert abs(common - truth) > 0.05


def test_pitch_change_correction_skips_a_dukf_restart(camera):
    """Across an IMU gap the DUKF restarts from the mounting attitude: that jump of the BEV pitch is
    no change the correction may take off (it would be metres), and the pair's forward variance
    holds its whole shift; elsewhere the correction acts."""
    d = preset_drive("curve", seed=3, duration=7.0, render="lazy", camera=camera)  # 100 Hz
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    t = d.imu_stamps - d.imu_stamps[0]
    gap = (4.55, 5.35)
    keep = (t < gap[0]) | (t > gap[1])  # a 0.8 s gap (> filter.max_imu_gap)
    runs, all_steps = {}, {}
    for on in (True, False):
        config = BevoConfig()
        config.odometry.pitch_change_correction = on
        odo = build_odometry(config, FUSED, camera=camera)
        steps = feed_engine(odo, d.imu_stamps[keep], d.gyro[keep], d.accel[keep], d.frame_stamps,
                            lambda k: images[k], trailing=False)
        assert odo.counters.imu_gaps == 1
        runs[on] = {round(s.stamp, 3): s.pitch_shift for s in steps}
        all_steps[on] = steps
    first_after = min(s for s in runs[True] if s > d.imu_stamps[0] + gap[1])
    assert not any(runs[False].values())  # off: nothing taken off
    diff = runs[True]
    print(f"\nshift taken off per frame (cm): {[round(float(v) * 100, 2) for v in diff.values()]}; first frame after the gap at "
          f"{first_after - d.imu_stamps[0]:.1f} s: {diff[first_after] * 100:.3f} cm")
    assert diff[first_after] == 0.0
    # never a jump's worth (1 deg would be 1.4 m); the low-pass's running-mean start moves the BEV
    # by up to ~0.1 deg per frame (measured: 17 cm at most)
    assert max(abs(v) for v in diff.values()) < 0.3
    assert sum(abs(v) > 1e-6 for v in diff.values()) >= 5  # and it does act
    k = next(i for i, s in enumerate(all_steps[True]) if round(s.stamp, 3) == first_after)
    before, after = all_steps[True][k - 1], all_steps[True][k]
    jump = after.pitch_roll_road[0] - before.pitch_roll_road[0]
    shift = build_odometry(BevoConfig(), FUSED, camera=camera)._shift_per_pitch_change * jump
    print(f"BEV pitch jump across the restart {math.degrees(jump):+.3f} deg: {shift * 100:.1f} cm; forward std "
          f"{math.sqrt(after.filter_inputs['forward_var']) * 100:.1f} cm")
    assert after.filter_inputs["forward_var"] >= shift**2


def test_pitch_change_correction_acts_from_the_start_and_the_dukf_start_stays_out_of_the_bev(camera):
    """At 10 Hz the correction acts from the first seconds on (a gate on the DUKF's variance kept it
    off for the first ~5 s of a 10 Hz drive and through accelerations). At 100 Hz, with the inertial
    speed input off, the DUKF's first convergence from the mounting attitude moves its pitch by 1 deg
    within the first frame pair, which is no change of the car: the share of its pull its excess
    variance says is its start is kept out of the BEV's attitude (the 7 s braking drive's start: the
    BEV pitch changes by 0.08 deg, the first pair's error is -7 cm; before, with the BEV following the
    DUKF, 0.65 deg and -54 cm with the pull gate leaving the pair alone, -104 cm without it). By
    default (fused item 17) the start's unknown acceleration keeps the DUKF on its gyro: 0.19 deg,
    the BEV 0.07 deg, -6 cm."""
    d10 = preset_drive("curve", seed=4, duration=3.0, render="lazy", camera=camera, imu_rate=10.0)
    steps = feed(engine(camera, "fused"), d10)
    acting = [abs(s.pitch_shift) > 1e-6 for s in steps[2:]]
    print(f"\n10 Hz: the correction acts on {sum(acting)} of {len(acting)} frame pairs after the first")
    assert sum(acting) >= 0.6 * len(acting)  # measured 22 of 29 (not: the DUKF converging at the start); 0 before

    d100 = preset_drive("braking", seed=1, duration=7.0, render="lazy", camera=camera)
    n = int(np.searchsorted(d100.imu_stamps, d100.frame_stamps[2])) + 1  # the first three frames
    # With the inertial speed input off the DUKF takes the accelerometer at its start (the variance-
    # only model of its forward acceleration): the case. With it on (fused item 17) the unknown
    # acceleration of a start keeps the DUKF on its gyro: no jump to keep out.
    for name, learned, converges in (("input off", FUSED_NO_INERTIAL, True), ("default", FUSED, False)):
        first = feed_engine(engine(camera, "fused", learned), d100.imu_stamps[:n], d100.gyro[:n], d100.accel[:n],
                            d100.frame_stamps[:3], d100.image, trailing=False)
        dukf_change = first[1].rpy[1] - first[0].rpy[1]
        bev_change = first[1].pitch_roll_road[0] - first[0].pitch_roll_road[0]
        error = first[1].measured_motion[0] - d100.relative_motion[0, 0]
        print(f"100 Hz, {name}, first pair: DUKF pitch {math.degrees(dukf_change):+.2f} deg, BEV pitch "
              f"{math.degrees(bev_change):+.2f} deg, forward error {error * 100:+.1f} cm")
        if converges:
            assert abs(dukf_change) > math.radians(0.5)  # the start's convergence happens
            assert abs(bev_change) < 0.2 * abs(dukf_change)
        else:
            assert abs(bev_change) < math.radians(0.2)
        assert abs(error) < 0.15


def test_pitch_change_gate_is_a_rate(camera):
    """The gate on the DUKF's pull scales with the frame interval: 0.05 deg of pull over a 10 Hz
    pair is small (the correction acts), over a 30 Hz pair it is a start's convergence spread over
    several short pairs (the correction waits)."""
    odo = engine(camera, "fused")
    odo._prev_pitch = (0.0, 0.0, 0, (0.0, 0.0))  # previous frame: BEV pitch, DUKF pitch, DUKF start, pull sums
    state = ((0.0, 0.0), (1e-6, 0.0, 1e-6))
    pull = math.radians(0.05)
    acts = odo._pitch_change_shift(1e-3, state, 0, pull, 0.1)
    waits = odo._pitch_change_shift(1e-3, state, 0, pull, 1 / 30)
    assert acts == pytest.approx(odo._shift_per_pitch_change * 1e-3) and acts != 0.0
    assert waits == 0.0
    assert odo._pitch_change_shift(1e-3, state, 1, 0.0, 0.1) == 0.0  # another DUKF start: never


def test_frame_clock_reads_jitter_as_jitter():
    """Stamps of a 0.1036 s camera quantised to 10 ms (KITTI frames timed by the OXTS clock): the
    clock gives the period back to < 2 ms, a dropped frame as two periods, a real rate change at
    once; exact stamps stay exact; window 0 passes the stamps through."""
    from bevo_ros.core.frame_clock import FrameClock

    period = 0.1036
    true = 1000.0 + period * np.arange(60)
    stamps = np.round(true / 0.01) * 0.01
    clock = FrameClock(20)
    raw = np.diff(stamps)
    out = np.array([clock.interval(float(dt)) for dt in raw])
    print(f"\nstamped intervals {raw.min():.3f}..{raw.max():.3f} s; clock after 10 frames "
          f"{out[10:].min():.4f}..{out[10:].max():.4f} s")
    assert raw.max() - raw.min() > 0.009  # +-5 % of the period
    assert np.abs(out[10:] - period).max() < 0.002
    assert clock.interval(float(2 * period)) == pytest.approx(2 * period, abs=0.004)  # a dropped frame
    assert clock.interval(0.05) == 0.05 and clock.period == 0.05  # the camera now runs at 20 Hz
    exact = FrameClock(20)
    assert all(exact.interval(0.1) == pytest.approx(0.1, abs=1e-12) for _ in range(30))
    assert FrameClock(0).interval(0.093) == 0.093


def test_frame_clock_keeps_stamp_jitter_out_of_the_motion(camera):
    """KITTI-like synced data: a 10 Hz IMU and the frames share one clock whose stamps jitter by
    +-10 ms (the OXTS clock), while images and IMU were taken on the true 10 Hz grid. With the
    frame clock the per-frame error stays near that of exact stamps."""
    d = preset_drive("curve", seed=4, duration=5.0, render="lazy", camera=camera, imu_rate=10.0)
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    assert np.array_equal(d.imu_stamps, d.frame_stamps)  # synced, one record per frame
    jittered = d.frame_stamps + 0.01 * np.random.default_rng(0).integers(-1, 2, len(d.frame_stamps))
    rows, yaws = {}, {}
    for window, stamps in ((20, d.frame_stamps), (20, jittered), (0, jittered)):
        config = BevoConfig()
        config.odometry.frame_clock_window = window
        odo = build_odometry(config, FUSED, camera=camera)
        steps = feed_engine(odo, stamps, d.gyro, d.accel, stamps, lambda k: images[k], trailing=False)
        est = np.array([s.motion for s in steps[1:]])
        assert len(est) == len(d.relative_motion)
        rows[window, stamps is jittered] = float(np.sqrt(np.mean((est[:, 0] - d.relative_motion[:, 0]) ** 2)))
        yaws[window, stamps is jittered] = float(np.degrees(np.sqrt(np.mean((est[:, 2] - d.relative_motion[:, 2]) ** 2))))
    print(f"\nforward RMSE: exact stamps {rows[20, False] * 100:.2f} cm; jittered stamps with the clock "
          f"{rows[20, True] * 100:.2f} cm, without {rows[0, True] * 100:.2f} cm; yaw RMSE {yaws[20, False]:.3f} / "
          f"{yaws[20, True]:.3f} / {yaws[0, True]:.3f} deg")
    assert rows[20, True] < 0.6 * rows[0, True]
    assert rows[20, True] < 1.5 * rows[20, False] + 0.01
    # the gyro's yaw over the frame's interval, not the stamped one
    assert yaws[20, True] < 1.3 * yaws[20, False] and yaws[20, True] < 0.6 * yaws[0, True]


def test_attitude_is_interpolated_to_the_frame_stamp(camera):
    """A 10 Hz IMU whose stamps jitter by +-10 ms against exact frame stamps (KITTI: OXTS stamps
    beside times.txt): the last IMU sample before a frame is often the previous frame's. With the
    attitude interpolated to the frame stamp the error stays near that of exact stamps (measured
    4.2 cm exact, 6.3 jittered; before the DUKF's start was kept out of the BEV 7.9 and 10.3; 18.1 cm
    jittered when the previous sample's attitude was used)."""
    d = preset_drive("curve", seed=4, duration=8.0, render="lazy", camera=camera, imu_rate=10.0)
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    jittered = d.imu_stamps + 0.01 * np.random.default_rng(0).integers(-1, 2, len(d.imu_stamps))
    rmse = {}
    for label, stamps in (("exact", d.imu_stamps), ("jittered", jittered)):
        odo = engine(camera, "fused")
        steps = feed_engine(odo, stamps, d.gyro, d.accel, d.frame_stamps, lambda k: images[k], trailing=True)
        # a frame stamped before the first IMU sample (jittered 10 ms late) has no attitude: dropped
        first = int(np.searchsorted(d.frame_stamps, steps[0].stamp))
        assert first == int(np.sum(d.frame_stamps < stamps[0])) and len(steps) == len(d.frame_stamps) - first
        est = np.array([s.motion for s in steps[1:]])
        rmse[label] = float(np.sqrt(np.mean((est[:, 0] - d.relative_motion[first:, 0]) ** 2)))
    print(f"\nforward RMSE: IMU stamps exact {rmse['exact'] * 100:.2f} cm, jittered {rmse['jittered'] * 100:.2f} cm")
    assert rmse["jittered"] < 1.6 * rmse["exact"] and rmse["jittered"] < 0.09


@pytest.mark.slow
def test_pitch_change_correction_on_an_urban_drive(camera):
    """The 10 Hz urban preset (a KITTI-like 10 Hz IMU; braking into a 90 deg turn, down to 0.1 m
    per frame): the correction removes the BEV pitch changes the engine itself made (road-tilt
    low-pass, suspension model), and the per-frame error and drift fall (docs/FUSED_ODOMETRY.md has the
    other presets)."""
    rows = {}
    for name, duration in (("urban", 26.0),):  # the README's preset, whole
        d = preset_drive(name, seed=1, duration=duration, render="lazy", camera=camera, imu_rate=10.0)
        images = [d.image(k) for k in range(len(d.frame_stamps))]
        for on in (True, False):
            config = BevoConfig()
            config.odometry.pitch_change_correction = on
            rows[name, on] = scores(feed(build_odometry(config, FUSED, camera=camera), d, images), d)
        print(f"\n{name}: corrected {rows[name, True]}\n{name}: not corrected {rows[name, False]}")
    for name in ("urban",):
        # measured 7.4 vs 14.1 % per frame and 0.57 vs 3.03 % drift (its first 16 s alone: 10.5 vs 16.0 %,
        # but 2.0 vs 1.9 % drift, a short drive's drift being a few frames' luck)
        assert rows[name, True]["trans_pct"] < 0.7 * rows[name, False]["trans_pct"]
        assert rows[name, True]["drift"] < 0.5 * rows[name, False]["drift"]
        assert rows[name, True]["yaw"] <= 0.05


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PRESET_LIMITS))
def test_fused_beats_paper_on_hard_drives(name, camera):
    duration, att_max, trans_max, yaw_max, drift_max = PRESET_LIMITS[name]
    d = preset_drive(name, seed=1, duration=duration, render="lazy", camera=camera, road_tilt=True)
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    fused = scores(feed(engine(camera, "fused"), d, images), d)
    paper = scores(feed(engine(camera, "paper"), d, images), d)
    print(f"\n{name}: fused {fused}\n{name}: paper {paper}")
    assert max(fused["pitch"], fused["roll"]) <= att_max and fused["yaw"] <= yaw_max
    assert fused["trans_pct"] <= trans_max and fused["drift"] <= drift_max
    assert fused["yaw"] < paper["yaw"] / 5  # the gyro's yaw
    assert fused["trans_pct"] < 0.3 * paper["trans_pct"] and fused["drift"] < 0.3 * paper["drift"]
    # the covariance it publishes is about right (measured here: mean NEES 0.7-2.7 where 3 is
    # consistent; the paper mode's 4.6-144)
    assert 0.5 < fused["nees_mean"] < 8.0 and fused["nees_mean"] < paper["nees_mean"], (fused, paper)


@pytest.mark.slow
def test_fused_holds_over_crests_and_sags(camera):
    """The ``curve`` preset over seeded crests and sags (``vertical_curves``: the IMU feels the
    slope's changes, the images show the road ahead bent by them, 3.7 cm RMS off the plane 15 m
    ahead): the fused engine stays usable and far ahead of the paper's, its covariance still about
    right. Measured (10 s, half-size camera, 100 Hz IMU): 6.2 % per frame, 1.4 % drift, 0.025 deg
    yaw, mean NEES 2.6; the same drive on a plane 2.4 %, 1.2 %; paper mode 19.3 %, 15.6 %."""
    d = preset_drive("curve", seed=1, duration=10.0, render="lazy", camera=camera, vertical_curves=True)
    p = d.road_profile
    bend = np.sqrt(np.mean([float(p.height_ahead(s)(np.array([15.0]))[0][0]) ** 2 for s in p.frame_distance]))
    assert bend > 0.02  # m: the road ahead does bend
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    fused = scores(feed(engine(camera, "fused"), d, images), d)
    paper = scores(feed(engine(camera, "paper"), d, images), d)
    print(f"\nroad 15 m ahead {bend * 100:.1f} cm RMS off the plane\nfused {fused}\npaper {paper}")
    assert fused["trans_pct"] <= 9.0 and fused["drift"] <= 3.0 and fused["yaw"] <= 0.04
    assert fused["trans_pct"] < 0.5 * paper["trans_pct"] and fused["drift"] < 0.3 * paper["drift"]
    assert 0.5 < fused["nees_mean"] < 8.0


@pytest.mark.slow
def test_the_bev_reaches_highway_speeds(camera):
    """38 m/s (137 km/h) from a cold start: 3.8 m a frame at 10 Hz, 38 % of the BEV's 10 m. The
    consecutive BEVs' common road shrinks with the speed and the correlation's peak with it (peak
    quality 0.36 at 20 m/s, 0.15 at 38, 0.10 at 46); past ~4.2 m a frame a cold start locks onto a
    wrong peak. Measured (5 s, half-size camera, 100 Hz IMU): 6.4 % per frame, 3.4 % drift, mean
    NEES 1.5; the same drive at 46 m/s reads 77 % short, and at 38 m/s with
    ``bev.metres_per_pixel`` 0.08 (an 8 m BEV, better in town: README, Limitations) 65 %. This
    holds the BEV's reach against tuning for the city. Frames past ``REACH_SHARE`` (40 %) of the BEV's
    extent are counted (``beyond_reach``, a WARN in /diagnostics): none here (3.8 m a frame), every frame
    but the first few once the share is 30 % (3 m); measured at 42 m/s from a cold start, 35 of 50."""
    import bevo_ros.core.odometry as odometry

    d = make_drive(seed=1, duration=5.0, camera=camera, render="lazy", speed_range=(38.0, 38.0),
                   speed_variation=0.0, curvature=0.3)
    assert abs(np.linalg.norm(d.relative_motion[:, :2], axis=1).mean() - 3.8) < 0.05  # m a frame
    images = [d.image(k) for k in range(d.num_frames)]
    odo = engine(camera, "fused")
    fused = scores(feed(odo, d, images), d)
    print(f"\n38 m/s from a cold start: {fused}")
    assert fused["trans_pct"] <= 10.0 and fused["drift"] <= 6.0 and fused["yaw"] <= 0.04
    assert 0.3 < fused["nees_mean"] < 8.0
    assert odo.counters.beyond_reach <= 5 and odo.reach == pytest.approx(4.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(odometry, "REACH_SHARE", 0.3)
        odo = engine(camera, "fused")
        assert odo.reach == pytest.approx(3.0)
        feed(odo, d, images)
    print(f"past 30 % of the BEV: {odo.counters.beyond_reach} of {d.num_frames - 1} frames")
    assert odo.counters.beyond_reach >= 0.8 * (d.num_frames - 1)


def test_black_frame_does_not_move_a_still_vehicle(camera):
    """A frame without texture is rejected (counted) and the pose carried by the motion filter."""
    d = preset_drive("braking", seed=2, duration=1.5, render="lazy", camera=camera)
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    still = images[0]
    imgs = [still] * len(images)
    imgs[8] = np.zeros_like(still)
    # A vehicle at rest: gravity only, no rotation.
    for i in range(len(d.imu_stamps)):
        d.gyro[i] = 0.0
        d.accel[i] = [0.0, 0.0, 9.80665]
    odo = engine(camera, "fused")
    steps = feed(odo, d, imgs)
    moves = np.array([np.linalg.norm(s.motion[:2]) for s in steps])
    print(f"\nper-frame motion max {moves.max():.4f} m; rejected textureless {odo.counters.rejected_textureless}")
    assert moves.max() < 0.2
    assert odo.counters.rejected_textureless >= 1
    rejected = [e for e in odo.take_events() if e.kind == "rejected_textureless"]  # what the node reports
    assert len(rejected) == odo.counters.rejected_textureless and rejected[0].stamp == float(d.frame_stamps[8])
    assert np.linalg.norm(steps[-1].position[:2]) < 0.2


def test_interval_rate_rules():
    from bevo_ros.core.rate_integration import interval_rate

    # interval means are the interval's rate as they are
    assert interval_rate("interval_mean", [1.0, 2.0], [5.0, 5.0], [9.0, 9.0], 0.1, 0.1) == [1.0, 2.0]
    # instantaneous: exact for a quadratic rate r(t) = 1 + 2 t + 3 t^2 on unequal steps 0 -> 0.15 -> 0.25
    r = lambda t: 1 + 2 * t + 3 * t * t  # noqa: E731
    exact = ((0.25 + 0.25**2 + 0.25**3) - (0.15 + 0.15**2 + 0.15**3)) / 0.1
    assert interval_rate("instantaneous", [r(0.25)], [r(0.15)], [r(0.0)], 0.1, 0.15)[0] == pytest.approx(exact, rel=1e-12)
    # the trapezoid without an earlier sample, or across a gap (no extrapolation over it)
    assert interval_rate("instantaneous", [2.0], [1.0], None, 0.1, None) == [1.5]
    assert interval_rate("instantaneous", [2.0], [1.0], [7.0], 0.1, 0.5) == [1.5]
    with pytest.raises(ValueError, match="sampling"):
        interval_rate("averaged", [1.0], [1.0], None, 0.1, None)


@pytest.mark.parametrize("sampling", ["interval_mean", "instantaneous"])
def test_engine_integrates_the_gyro_by_its_sampling(sampling):
    """The engine's own bookkeeping of the last samples (a start, unequal steps, a gap that
    restarts the DUKF, a step 10x shorter than the one before): a quadratic yaw rate integrates
    exactly, the trapezoid only right after a (re)start and across the uneven step."""
    rate = lambda t: 0.1 + 0.5 * t - 0.3 * t * t  # noqa: E731
    integral = lambda t: 0.1 * t + 0.25 * t * t - 0.1 * t**3  # noqa: E731
    config = BevoConfig()
    config.filter.gyro_sampling = sampling
    odo = build_odometry(config, FUSED, camera=kitti_like_camera())
    stamps = [0.0, 0.1, 0.17, 0.3, 0.38, 0.5, 1.2, 1.3, 1.37, 1.5, 1.6, 1.61, 1.7]
    expected, trapezoid_steps = 0.0, {1, 7, 11, 12}  # after the start, after the gap, 10x shorter, 9x longer
    for i, t in enumerate(stamps):
        h = t - stamps[i - 1] if i else None
        if sampling == "interval_mean":
            sample = (integral(t) - integral(stamps[i - 1])) / h if i else rate(t)
        else:
            sample = rate(t)
        odo.add_imu(t, [0.0, 0.0, sample], [0.0, 0.0, 9.80665])
        if i and h <= config.filter.max_imu_gap:
            if sampling == "instantaneous" and i in trapezoid_steps:
                expected += 0.5 * (rate(t) + rate(stamps[i - 1])) * h
            else:
                expected += integral(t) - integral(stamps[i - 1])
        assert odo._yaw_cum == pytest.approx(expected, abs=1e-12), (sampling, t)
    assert odo.counters.imu_gaps == 1


@pytest.mark.parametrize("sampling", ["interval_mean", "instantaneous"])
def test_gyro_sampling_setting_matches_the_imu(sampling):
    """The DUKF's pitch change per 10 Hz IMU interval on the bumpy preset (noise-free IMU) follows
    the truth several times closer with the setting that matches the gyro than with the other."""
    d = preset_drive("bumpy", seed=1, duration=8.0, render=False, noise=False, imu_rate=10.0, gyro_sampling=sampling)
    truth = np.diff(d.imu_pitch_roll_gravity[:, 0])
    errors = {}
    for setting in ("interval_mean", "instantaneous"):
        config = BevoConfig()
        config.filter.gyro_sampling = setting
        odo = build_odometry(config, FUSED, camera=kitti_like_camera())
        pitch = []
        for k, stamp in enumerate(d.imu_stamps):
            odo.add_imu(float(stamp), d.gyro[k], d.accel[k])
            pitch.append(odo.pitch_roll[0])
        errors[setting] = float(np.degrees(np.sqrt(np.mean((np.diff(pitch)[3:] - truth[3:]) ** 2))))
    other = "instantaneous" if sampling == "interval_mean" else "interval_mean"
    print(f"\n{sampling} gyro: pitch change error per interval {errors[sampling]:.4f} deg with the matching "
          f"setting, {errors[other]:.4f} deg with {other}")
    assert errors[sampling] < 0.5 * errors[other]


# ------------------------------------------------------------------------------ real IMU
@pytest.mark.kitti
@pytest.mark.parametrize("drive", ["0016", "0018", "0020", "0027"])
def test_kitti_gyro_samples_are_interval_means(kitti_root, drive):
    """Why ``filter.gyro_sampling`` defaults to ``interval_mean``: on the real OXTS drives the
    unit's own pitch and heading change over each 10 Hz interval is the interval's end sample
    times its length, far closer than the trapezoid of the two end samples (which is right for
    rates sampled at their stamps)."""
    from bevo_ros.core.rate_integration import interval_rate
    from bevo_ros.datasets.kitti import read_oxts

    ox = read_oxts(kitti_root / "raw" / "2011_09_30" / f"2011_09_30_drive_{drive}_sync" / "oxts")
    t, g, p, r = ox.stamps, ox.gyro, ox.pitch, ox.roll
    rates = np.stack([g[:, 1] * np.cos(r) - g[:, 2] * np.sin(r),  # pitch and heading rates (Euler kinematics)
                      (g[:, 1] * np.sin(r) + g[:, 2] * np.cos(r)) / np.cos(p)], -1)
    change = np.diff(np.stack([p, np.unwrap(ox.field("yaw"))], -1), axis=0)
    errors = {}
    for rule in ("interval_mean", "instantaneous"):
        est = np.array([np.array(interval_rate(rule, rates[k + 1], rates[k], rates[k - 1] if k else None,
                                               t[k + 1] - t[k], t[k] - t[k - 1] if k else None)) * (t[k + 1] - t[k])
                        for k in range(len(t) - 1)])
        ok = np.abs(np.diff(t) - 0.1) < 0.05
        errors[rule] = np.degrees(np.sqrt(np.mean((est[ok] - change[ok]) ** 2, axis=0)))
    print(f"\n{drive}: per-interval (pitch, heading) change error RMS, deg: interval mean "
          f"{errors['interval_mean'].round(4)}, instantaneous (quadratic) {errors['instantaneous'].round(4)}")
    assert (errors["interval_mean"] < 0.6 * errors["instantaneous"]).all()
    assert errors["interval_mean"][0] < 0.03


@pytest.mark.kitti
@pytest.mark.parametrize("drive", ["0016", "0018", "0020", "0027"])
def test_gravity_attitude_on_real_drives(kitti_root, drive):
    """The shared OXTS drives (real bends, stops): the engine's DUKF with the unit's forward speed
    standing in for wheel odometry stays within 0.5 deg RMS of the unit's own pitch and roll."""
    from bevo_ros.datasets.kitti import read_oxts

    ox = read_oxts(kitti_root / "raw" / "2011_09_30" / f"2011_09_30_drive_{drive}_sync" / "oxts")
    config = BevoConfig()
    config.camera = CameraSettings(fx=700, fy=700, cx=600, cy=180, width=1226, height_px=370)
    t = ox.stamps - ox.stamps[0]
    vf = ox.field("vf")
    results = {}
    for label, use_speed in (("fused", True), ("paper", False)):
        config.odometry.mode = "fused" if use_speed else "paper"
        odo = build_odometry(config, FUSED if use_speed else PAPER)
        out = []
        for i in range(len(t)):
            if use_speed:
                odo.add_speed(t[i], vf[i], 0.05**2)
            odo.add_imu(t[i], ox.gyro[i], ox.accel[i])
            out.append(odo.pitch_roll)
        out = np.array(out)
        results[label] = np.degrees(np.sqrt(np.mean((out - np.stack([ox.pitch, ox.roll], -1)) ** 2, axis=0)))
    print(f"\n{drive}: fused pitch/roll RMS {results['fused'].round(2)} deg; paper {results['paper'].round(2)} deg")
    assert results["fused"].max() <= 0.5
    assert results["fused"].mean() < results["paper"].mean()


def _road_pitch_error_on_real_drive(ox, config, learned) -> np.ndarray:
    """The engine's road-relative pitch (IMU only, the unit's speed as wheel odometry) minus the
    road pitch the unit's velocity implies, degrees, at speeds above 2 m/s after the first 5 s."""
    odo = build_odometry(config, learned)
    t = ox.stamps - ox.stamps[0]
    vf, vl, vu = ox.field("vf"), ox.field("vl"), ox.field("vu")
    est = []
    for i in range(len(t)):
        odo.add_speed(t[i], vf[i], 0.05**2)
        odo.add_imu(t[i], ox.gyro[i], ox.accel[i])
        est.append(odo.road_pitch_roll[0])
    # The road's slope from the velocity (climbing is nose up, negative pitch); the body's heave
    # on its springs is in vu too, and a zero-phase 0.7 s Gaussian takes it out.
    speed = np.hypot(vf, vl)
    slope = -np.arctan2(vu, speed)
    sigma = 7.0  # samples at 10 Hz
    k = np.exp(-0.5 * (np.arange(-28, 29) / sigma) ** 2)
    slope = np.convolve(np.pad(slope, 28, mode="edge"), k / k.sum(), mode="valid")
    ref = ox.pitch - slope  # the unit's pitch on the road, plus its constant mounting
    ok = (speed > 2.0) & (t > 5.0)
    return np.degrees(np.array(est)[ok] - (ref[ok] - ref[ok].mean()))


@pytest.mark.kitti
def test_road_pitch_on_real_drives(kitti_root):
    """Issue 9 item 2 on real data: the road-relative pitch the BEV gets, against the road pitch
    the OXTS unit's own velocity implies (its pitch minus the slope atan(vu / v)), on the four
    shared drives. The defaults (road-tilt low-pass 1 s, suspension pitch 0.004 rad per m/s^2)
    beat the previous ones (2 s, no suspension pitch)."""
    from bevo_ros.datasets.kitti import read_oxts

    config = BevoConfig()
    config.camera = CameraSettings(fx=700, fy=700, cx=600, cy=180, width=1226, height_px=370)
    old = BevoConfig()
    old.camera = config.camera
    old.filter.road_tilt_time_constant = 2.0
    old_learned = replace(FUSED, suspension_gradients=(0.0, FUSED.suspension_gradients[1]))
    rms, rms_old = [], []
    for drive in ("0016", "0018", "0020", "0027"):
        ox = read_oxts(kitti_root / "raw" / "2011_09_30" / f"2011_09_30_drive_{drive}_sync" / "oxts")
        rms.append(float(np.sqrt(np.mean(_road_pitch_error_on_real_drive(ox, config, FUSED) ** 2))))
        rms_old.append(float(np.sqrt(np.mean(_road_pitch_error_on_real_drive(ox, old, old_learned) ** 2))))
    print(f"\nroad pitch RMS error (deg) on 0016/0018/0020/0027: {np.round(rms, 3)} (mean {np.mean(rms):.3f}); "
          f"tau 2 s without suspension pitch: {np.round(rms_old, 3)} (mean {np.mean(rms_old):.3f})")
    assert max(rms) <= 0.3 and np.mean(rms) <= 0.2
    assert np.mean(rms) < 0.85 * np.mean(rms_old)


# ------------------------------------------------------------------------------ learning the filter
def _measurement_drive(n: int, seed: int, noise=(0.05, 0.02, 0.003), accel: bool = False):
    """Recorded filter inputs of a car at 7-13 m/s weaving (exact truth), with measurement noise
    unlike the filter's defaults (the correlation's forward motion 5 cm, lateral 2 cm). ``accel``:
    with the inertial speed input (the interval's mean acceleration, 0.3 m/s^2 noise, 0.05 bias)."""
    rng = np.random.default_rng(seed)
    dt = 0.1
    t = np.arange(n) * dt
    v, w = 10 + 3 * np.sin(0.3 * t), 0.1 * np.sin(0.2 * t)
    truth = np.stack([v * dt, v * dt * np.tan(w * dt / 2), w * dt], -1)
    a = 0.9 * np.cos(0.3 * (t - dt / 2)) + 0.05 + np.random.default_rng(seed + 1000).normal(0, 0.3, n)
    inputs = [dict(dt=dt, gyro_yaw=truth[i, 2] + 0.002 * dt + rng.normal(0, 1e-4),
                   forward=truth[i, 0] + rng.normal(0, noise[0]), forward_var=0.01**2,
                   lateral=truth[i, 1] + rng.normal(0, noise[1]), lateral_var=0.02**2,
                   rotation=truth[i, 2] + rng.normal(0, noise[2]), rotation_var=noise[2] ** 2, quality=0.5,
                   **(dict(imu_accel=float(a[i]), imu_accel_var=0.0) if accel else {}))
              for i in range(n)]
    return inputs, truth


def test_vehicle_noise_gradients_are_exact():
    from bevo_ros.training.vehicle import TRAINED, motion_nll, replay, trained_fields, _noise_with

    inputs, truth = _measurement_drive(12, 0, accel=True)  # the inertial speed input's density too
    t = torch.as_tensor(truth, dtype=torch.float64)
    base = VehicleNoise()
    assert trained_fields(base) == TRAINED and "imu_accel_density" in TRAINED
    assert "imu_accel_density" not in trained_fields(VehicleNoise(imu_accel_density=0.0))  # off stays off
    p0 = torch.tensor([math.log(getattr(base, k)) for k in TRAINED], dtype=torch.float64, requires_grad=True)

    def f(p):
        m, v = replay(_noise_with(base, p), inputs)
        return motion_nll(m, v, t)

    assert torch.autograd.gradcheck(f, (p0,), eps=1e-6, atol=1e-6)
    p = p0.detach().clone().requires_grad_(True)
    f(p).backward()
    assert p.grad[TRAINED.index("imu_accel_density")] != 0.0  # it does reach the NLL


def test_learning_beats_the_default_noise_on_held_out_frames():
    from bevo_ros.training.vehicle import fit_vehicle_noise, motion_nll, replay

    train, held_out = _measurement_drive(200, 1), _measurement_drive(200, 2)
    fit = fit_vehicle_noise([train], steps=60, lr=0.2, log=lambda _: None)
    t = torch.as_tensor(held_out[1], dtype=torch.float64)
    scores = {}
    for name, noise in (("default", VehicleNoise()), ("learned", fit.noise)):
        m, v = replay(noise, held_out[0])
        scores[name] = (float(motion_nll(m, v, t)), ((m - t) ** 2).mean(0).sqrt().numpy())
    print(f"\nheld-out NLL default {scores['default'][0]:.3f} -> learned {scores['learned'][0]:.3f}; "
          f"RMSE dx/dy/dyaw default {scores['default'][1]} learned {scores['learned'][1]}")
    assert scores["learned"][0] < scores["default"][0] - 0.5
    assert scores["learned"][1][1] < 0.2 * scores["default"][1][1]  # lateral: the arc prior is exact here
    assert scores["learned"][1][0] <= scores["default"][1][0] * 1.02


def test_replay_reproduces_the_engine(camera):
    """Training replays exactly what the engine computed (same inputs, same filter), with the
    configured gates: a tight ``odometry.gate`` and a high ``min_quality`` are the replay's too
    (``config.vehicle_noise``; the defaults' replay differs)."""
    from bevo_ros.config import vehicle_noise
    from bevo_ros.training.vehicle import replay

    d = preset_drive("curve", seed=3, duration=2.0, render="lazy", camera=camera)
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    steps = feed(engine(camera, "fused"), d, images)
    m, _ = replay(VehicleNoise(**FUSED.vehicle), [s.filter_inputs for s in steps[1:]])
    assert np.abs(m.numpy() - np.array([s.motion for s in steps[1:]])).max() < 1e-9

    config = BevoConfig()
    config.odometry.gate, config.odometry.min_quality, config.odometry.rotation_gate = 1.0, 0.5, 1e-4  # tight (gate >= 1)
    odo = build_odometry(config, FUSED, camera=camera)
    steps = feed(odo, d, images)
    c = odo.counters
    assert c.rejected_translation + c.rejected_textureless > 0
    inputs = [s.filter_inputs for s in steps[1:]]
    engine_motion = np.array([s.motion for s in steps[1:]])
    m, _ = replay(vehicle_noise(config, FUSED), inputs)
    assert np.abs(m.numpy() - engine_motion).max() < 1e-9
    m, _ = replay(VehicleNoise(**FUSED.vehicle), inputs)
    assert np.abs(m.numpy() - engine_motion).max() > 1e-6


def test_replay_reproduces_the_engine_across_a_dukf_restart(camera):
    """An IMU gap longer than ``max_imu_gap`` restarts the DUKF, and the engine forgets the motion
    filter's accelerometer bias (the inertial input's gravity starts anew): the frame's filter inputs
    say so and the replay does the same, so training fits the filter the engine ran."""
    from bevo_ros.training.vehicle import RESETS, replay

    d = preset_drive("curve", seed=3, duration=3.0, render="lazy", camera=camera, imu_rate=10.0)
    keep = (d.imu_stamps < d.imu_stamps[0] + 1.2) | (d.imu_stamps > d.imu_stamps[0] + 1.9)  # a 0.7 s gap
    images = [d.image(k) for k in range(len(d.frame_stamps))]
    odo = engine(camera, "fused")
    steps = feed_engine(odo, d.imu_stamps[keep], d.gyro[keep], d.accel[keep], d.frame_stamps,
                        lambda k: images[k], trailing=False)
    assert odo.counters.imu_gaps == 1
    inputs = [s.filter_inputs for s in steps[1:]]
    assert sum(bool(i["forget_accel_bias"]) for i in inputs[1:]) == 1  # the restart (frame 1: the start's, a no-op)
    engine_motion = np.array([s.motion for s in steps[1:]])
    m, _ = replay(VehicleNoise(**FUSED.vehicle), inputs)
    assert np.abs(m.numpy() - engine_motion).max() < 1e-9
    ignored = [{k: (False if k in RESETS else v) for k, v in i.items()} for i in inputs]
    m, _ = replay(VehicleNoise(**FUSED.vehicle), ignored)
    assert np.abs(m.numpy() - engine_motion).max() > 1e-9  # the reset matters


def test_learning_the_suspension_beats_the_default_on_a_held_out_drive():
    """Issue 9 item 6 for the suspension gradients: the synthetic car dives 0.3 deg per m/s^2
    (0.00524 rad) when it brakes, the default (KITTI's car) says 0.004. Searched on one braking
    drive (seed 1, 10 Hz IMU, half-resolution camera) by the engine's per-frame translation error,
    the pitch gradient comes out near the car's, the roll one (no bend to tell) stays, and the
    engine's per-frame error falls on the training drive and on a held-out one (seed 2).
    Measured: pitch 0.00667, training 5.98 -> 3.87 cm, held out 15.75 -> 14.28 cm per frame."""
    from bevo_ros.training.suspension import fit_suspension

    cam = kitti_like_camera(scale=0.5)
    train, held_out = (preset_drive("braking", seed=s, imu_rate=10.0, camera=cam, render="lazy").to_recording()
                       for s in (1, 2))
    fit = fit_suspension([(train, len(train) - 1), (held_out, 0)], BevoConfig(), FUSED, evals_per_axis=6)
    print(f"\nsuspension fit: {fit}")
    assert 0.0045 <= fit.gradients[0] <= 0.0075
    assert fit.gradients[1] == FUSED.suspension_gradients[1]
    assert fit.train_after < 0.8 * fit.train_before
    assert fit.validation_after < 0.95 * fit.validation_before


def test_behind_a_car_the_road_motion_is_kept():
    """Urban preset behind a car (10 Hz IMU, 13 s: the car ahead covers the BEV's centre from ~8.4 m,
    brakes first, pulls away first). Its correlation peak (it moves with the ego) outweighs the
    road's in many frames; the engine takes the peak nearest the motion filter's prediction and
    leaves what moves unlike it out of the correlation. Without that prior (the engine before),
    the same drive read the car's motion: 60 % per frame, 29 % drift; with it 9.1 % and 3.9 %."""
    from bevo_ros.datasets.synthetic import TrafficOptions

    cam = kitti_like_camera(scale=0.5)
    d = preset_drive("urban", seed=1, imu_rate=10, camera=cam, duration=13.0, render=True,
                     traffic=TrafficOptions(parked_spacing=0, oncoming_spacing=0))
    odo = engine(cam, "fused")
    with_prior = scores(feed(odo, d, d.images), d)
    blind = engine(cam, "fused")
    blind._shift_prior = lambda *args, **kwargs: None  # the highest peak, no weight: the old engine
    without = scores(feed(blind, d, d.images), d)
    print(f"behind a car: per frame {with_prior['trans_pct']:.1f} % (without the prior {without['trans_pct']:.1f}), "
          f"drift {with_prior['drift']:.2f} % ({without['drift']:.2f}), NEES {with_prior['nees_mean']:.2f}")
    assert with_prior["trans_pct"] < 15.0 and with_prior["drift"] < 6.0
    assert without["trans_pct"] > 2 * with_prior["trans_pct"]


def _clip_motions(odo, d, f0: int, f1: int) -> tuple[np.ndarray, np.ndarray]:
    """The engine started cold at frame ``f0`` through ``f1 - 1``, fed by stamp as a bag plays
    (frames rendered as needed). -> estimated and true ``(F - 1, 3)`` motions."""
    imu = (d.imu_stamps >= d.frame_stamps[f0] - 0.15) & (d.imu_stamps <= d.frame_stamps[f1 - 1] + 0.15)
    steps = feed_engine(odo, d.imu_stamps[imu], d.gyro[imu], d.accel[imu], d.frame_stamps[f0:f1],
                        lambda k: d.image(f0 + k), by_stamp=True)
    return np.array([s.motion for s in steps[1:]]), d.relative_motion[f0:f1 - 1]


def _drift_pct(est: np.ndarray, gt: np.ndarray) -> float:
    return motion_scores(est, gt)["drift"]


@pytest.mark.slow
def test_the_car_ahead_pulling_away_is_not_read_as_reversing():
    """Urban preset with traffic, a clip started cold 10.4 s in (5 s): the car ahead moves with
    the ego, its peak near zero shift, and pulling away it moves backwards in the BEV, as the road
    would if the car reversed. Followed, the ego goes backwards (unlocked: 120 % drift, 27 frames
    backwards; the clip from 10 s, which this test used before the DUKF's start was kept out of the
    BEV, now reads 1.2 % unlocked with 3 frames backwards). With the direction locked forward until
    a confirmed stop (``odometry.direction_lock``, the default): 2.4 %."""
    cam = kitti_like_camera(scale=0.5)
    d = preset_drive("urban", seed=1, imu_rate=10, camera=cam, render="lazy", traffic=True)
    runs = {}
    for lock in (True, False):
        config = BevoConfig()
        config.odometry.direction_lock = lock
        runs[lock] = _clip_motions(build_odometry(config, FUSED, camera=cam), d, 104, 155)
    (est, gt), (free, _) = runs[True], runs[False]
    locked_drift, free_drift = _drift_pct(est, gt), _drift_pct(free, gt)
    print(f"cold start behind a car: drift {locked_drift:.2f} % locked, {free_drift:.2f} % free; "
          f"backward frames {int((est[:, 0] < -0.05).sum())} / {int((free[:, 0] < -0.05).sum())}")
    assert locked_drift < 5.0 and not (est[:, 0] < -0.05).any()
    assert free_drift > 20.0


def test_a_cold_start_behind_a_car_moving_with_ours_reads_the_road(monkeypatch):
    """Bumpy preset with traffic from its start (8.5 m/s): the first frame pair's highest peak is the
    car ahead's, ~0 (it moves with the ego), and the motion filter has no prediction yet. The
    images' small flow (core/standstill, run because the correlation reads a near stop) says the
    car moved more than a stop allows (its coarse look reads beyond 0.15 m), so the road's peak
    beyond that least motion is taken: 0.85 m read for a true 0.80 m, 0.03 m without that check.
    (The motion filter then weighs it with the DUKF's start, as any first pair.)"""
    import bevo_ros.core.odometry as odometry

    cam = kitti_like_camera(scale=0.5)
    d = preset_drive("bumpy", seed=1, imu_rate=10, camera=cam, render="lazy", traffic=True)
    def first_measured(odo) -> np.ndarray:
        imu = d.imu_stamps <= d.frame_stamps[1]
        steps = feed_engine(odo, d.imu_stamps[imu], d.gyro[imu], d.accel[imu], d.frame_stamps[:2], d.image)
        return steps[1].measured_motion

    read, truth = first_measured(engine(cam, "fused")), d.relative_motion[0]
    monkeypatch.setattr(odometry, "MOVING_MARGIN", math.inf)
    blind = first_measured(engine(cam, "fused"))
    print(f"first pair: truth {truth[0]:.3f} m, read {read[0]:.3f} m (without the flow check {blind[0]:.3f} m)")
    assert abs(read[0] - truth[0]) < 0.1
    assert abs(blind[0] - truth[0]) > 0.4


def test_inertial_speed_input_takes_gravity_at_the_gyros_pitch(camera):
    """The inertial speed input (``imu_accel_density`` > 0, the default) removes gravity from the
    forward accelerometer at the DUKF's pitch less its accelerometer updates of the last
    ``INERTIAL_PULL_MEMORY``: what the DUKF misreads of a braking as tilt stays out of the
    acceleration, and what is left is the start's constant error, which the filter's bias state
    takes. Noise-free 10 Hz ``braking`` (-5 m/s^2 for 2.5 s): the input's error is 0.089 m/s^2
    before and 0.083 after the braking (g x the start's 0.47 deg: 0.080); at the DUKF's pitch it was
    0.039 before and 0.131 after (the braking's pull left in it), an error that changes, which no
    bias state holds."""
    d = preset_drive("braking", seed=1, duration=6.0, render="lazy", camera=camera, imu_rate=10.0, noise=False)
    steps = feed(engine(camera, "fused"), d)
    measured = np.array([s.filter_inputs["imu_accel"] for s in steps[2:]])
    truth = (np.diff(d.speed) / np.diff(d.frame_stamps))[1:]  # the interval's mean acceleration
    error = measured - truth
    braking = np.flatnonzero(truth < -0.01)
    before, after = error[2:braking[0] - 1], error[braking[-1] + 2:]
    start_error = GRAVITY * math.sin(-d.pitch_roll_gravity[0, 0])  # the DUKF starts at the mounting, 0
    print(f"\ninertial input error (m/s^2): before the braking {np.median(before):+.3f}, after {np.median(after):+.3f}, "
          f"the start's gravity error {start_error:+.3f}")
    assert len(before) >= 10 and len(after) >= 5
    assert abs(np.median(after) - np.median(before)) < 0.02  # measured 0.006; 0.092 at the DUKF's pitch
    assert abs(np.median(before) - start_error) < 0.02


def test_the_dukf_subtracts_the_motion_filters_acceleration(camera):
    """Fused item 17: with the inertial speed input on (the default) the DUKF subtracts the motion
    filter's forward acceleration from the accelerometer at that estimate's variance, instead of only
    widening its variance by the acceleration's size (the model with the input off). Noise-free
    10 Hz ``stop_and_go`` (8 s, stops and starts at 1.5-2 m/s^2): the gravity pitch's RMS error
    after the first second 0.64 deg, 1.27 with the input off (1.18 before item 17 with it on)."""
    d = preset_drive("stop_and_go", seed=1, duration=8.0, render="lazy", camera=camera, imu_rate=10.0, noise=False)
    images = [d.image(k) for k in range(d.num_frames)]
    rms = {}
    for name, learned in (("default", FUSED), ("input off", FUSED_NO_INERTIAL)):
        steps = feed(engine(camera, "fused", learned), d, images)
        err = np.array([s.rpy[1] for s in steps]) - d.pitch_roll_gravity[:len(steps), 0]
        rms[name] = math.degrees(float(np.sqrt(np.mean(err[10:] ** 2))))
    print(f"\ngravity pitch RMS error: default {rms['default']:.2f} deg, input off {rms['input off']:.2f} deg")
    assert rms["input off"] > 1.0  # the case: stops and starts read as tilt
    assert rms["default"] < 0.9


def test_the_dukf_subtracts_only_an_acceleration_the_accelerometer_took_part_in(camera):
    """Fused item 17 subtracts the motion filter's acceleration only after a frame whose filter step
    had the inertial input: the images' speed alone gives a dv/dt whose error the BEV's pitch feeds
    (item 1's loop). One accelerometer sample of a car at rest on the level, the filter's state saying
    2 m/s^2: subtracted, it reads as an 11.5 deg tilt and pulls the DUKF; without the inertial input
    behind that number, the sample reads level."""
    from bevo_ros.core.vehicle_filter import VehicleState

    pulls = {}
    for had_input in (True, False):
        odo = engine(camera, "fused")
        level = [0.0, 0.0, GRAVITY]
        for k in range(3):
            odo.add_imu(0.1 * k, [0.0, 0.0, 0.0], level)
        before = odo.pitch_roll[0]
        odo._vstate = VehicleState([0.0, 2.0, 0.0, 0.0], [[0.01 * (i == j) for j in range(4)] for i in range(4)])
        odo._accel_has_inertial = had_input
        odo.add_imu(0.3, [0.0, 0.0, 0.0], level)
        pulls[had_input] = math.degrees(odo.pitch_roll[0] - before)
    print(f"\npitch pulled {pulls[True]:+.3f} deg with the inertial input behind the acceleration, "
          f"{pulls[False]:+.3f} deg without")
    assert abs(pulls[True]) > 0.5
    assert abs(pulls[False]) < 0.05


def test_forget_speed_keeps_the_biases():
    """``forget_speed``: speed and acceleration unknown again (zero, wide, uncorrelated), the yaw
    gyro's and the accelerometer's biases and their covariance kept; floats and ``(B,)`` tensors."""
    from bevo_ros.core.vehicle_filter import forget_speed

    s = initial_vehicle_state()
    s.x = [8.0, -1.0, 0.002, 0.05]
    s.P = [[0.1 * (i == j) + 0.01 for j in range(4)] for i in range(4)]
    f = forget_speed(s)
    assert f.x == [0.0, 0.0, 0.002, 0.05]
    assert f.P[0][0] == 900.0 and f.P[1][1] == 9.0 and f.P[0][1] == 0.0 and f.P[0][2] == 0.0 and f.P[3][1] == 0.0
    assert f.P[2][2] == s.P[2][2] and f.P[2][3] == s.P[2][3] == f.P[3][2]
    t = initial_vehicle_state(like=torch.zeros(2))
    t.x = [torch.full((2,), 8.0), torch.zeros(2), torch.full((2,), 0.002), torch.zeros(2)]
    ft = forget_speed(t)
    assert torch.equal(ft.x[0], torch.zeros(2)) and torch.equal(ft.x[2], torch.full((2,), 0.002))
    assert torch.equal(ft.P[0][0], torch.full((2,), 900.0))


def test_forget_accel_bias_keeps_the_motion():
    """``forget_accel_bias`` (a DUKF restart): the accelerometer bias unknown again (zero, the start's
    variance, uncorrelated), speed, acceleration, the yaw gyro's bias and their covariance kept."""
    from bevo_ros.core.vehicle_filter import forget_accel_bias

    s = initial_vehicle_state()
    s.x = [8.0, -1.0, 0.002, 0.05]
    s.P = [[0.1 * (i == j) + 0.01 for j in range(4)] for i in range(4)]
    f = forget_accel_bias(s)
    assert f.x == [8.0, -1.0, 0.002, 0.0]
    assert f.P[3][3] == pytest.approx(0.09) and f.P[3][0] == f.P[0][3] == 0.0 and f.P[2][3] == 0.0
    assert all(f.P[i][j] == s.P[i][j] for i in range(3) for j in range(3))
    t = initial_vehicle_state(like=torch.zeros(2))
    t.x = [torch.full((2,), 8.0), torch.zeros(2), torch.full((2,), 0.002), torch.full((2,), 0.05)]
    ft = forget_accel_bias(t)
    assert torch.equal(ft.x[0], torch.full((2,), 8.0)) and torch.equal(ft.x[3], torch.zeros(2))


def test_vehicle_fit_keeps_the_learned_files_other_numbers(monkeypatch):
    """A kept fit of the motion filter's noise writes the fitted fields over the learned file's own:
    the ones training does not fit (``accel_bias_walk_density``, ``image_rotation_std``) stay as the
    file had them (they fell back to the defaults before)."""
    import bevo_ros.training.suspension as suspension_training
    import bevo_ros.training.vehicle as vehicle_training

    inputs, truth = _measurement_drive(120, 1)
    monkeypatch.setattr(vehicle_training, "record_inputs", lambda sequence, config, learned: (inputs, truth))
    # the engine's judgement of the fit (test_vehicle_fit_is_judged_in_the_engine): clearly better
    monkeypatch.setattr(suspension_training, "validation_errors", lambda seqs, config, learned, split, memo=None: np.full(
        (2, 40), 0.05 if learned.vehicle["slip_std"] == FUSED.vehicle["slip_std"] else 0.04))

    class Recording:  # what the fit reads of a sequence besides its recorded inputs: its length
        def __len__(self) -> int:
            return len(inputs) + 1

    own = {"accel_bias_walk_density": 5e-3, "image_rotation_std": 0.03}
    learned = replace(FUSED, vehicle={**FUSED.vehicle, **own}, info=dict(FUSED.info))
    vehicle_training.fit_vehicle_on_sequences(learned, [Recording()], BevoConfig(), steps=20)
    assert "vehicle_filter_fit" in learned.info  # kept (else this test says nothing)
    assert {k: learned.vehicle[k] for k in own} == own
    assert learned.vehicle["slip_std"] != FUSED.vehicle["slip_std"]  # and the fitted ones moved


def test_vehicle_fit_is_judged_in_the_engine(monkeypatch, capsys):
    """A fit whose likelihood improves on the validation frames is still refused when the engine, run
    with it, reads those frames worse (the replay keeps the old noise's measurements; in the engine the
    noise moves the gates and the prediction too): the learned file's noise stays, and says why."""
    import bevo_ros.training.suspension as suspension_training
    import bevo_ros.training.vehicle as vehicle_training

    inputs, truth = _measurement_drive(120, 1)
    monkeypatch.setattr(vehicle_training, "record_inputs", lambda sequence, config, learned: (inputs, truth))
    monkeypatch.setattr(suspension_training, "validation_errors",
                        lambda seqs, config, learned, split, memo=None: np.full((2, 40), 0.05 if learned.vehicle == FUSED.vehicle
                                                                     else 0.07))

    class Recording:
        def __len__(self) -> int:
            return len(inputs) + 1

    learned = replace(FUSED, vehicle=dict(FUSED.vehicle), info=dict(FUSED.info))
    vehicle_training.fit_vehicle_on_sequences(learned, [Recording()], BevoConfig(), steps=20)
    out = capsys.readouterr().out
    assert "validation per-frame translation RMSE 0.0500 -> 0.0700 m" in out, out
    assert "vehicle filter: not clearly better in the engine (worse by" in out and "keeping the previous values" in out
    assert learned.vehicle == FUSED.vehicle and "vehicle_filter_fit" not in learned.info


def test_a_fast_camera_thinned_and_an_imu_clock_offset_taken_off(camera):
    """Other rigs: ``odometry.min_frame_interval`` processes a 30 Hz camera's frames as its every third
    (the same poses as feeding only those; the rest counted as skipped, no odometry), and
    ``odometry.imu_time_offset`` puts an IMU whose clock runs 12 ms ahead back on the images' clock
    (the same poses as the aligned stamps; uncorrected they differ)."""
    d = preset_drive("urban", seed=3, duration=3.0, render="lazy", camera=camera, imu_rate=90.0, frame_rate=30.0)
    images = [d.image(k) for k in range(len(d.frame_stamps))]

    def run(min_interval=0.0, offset=0.0, imu_shift=0.0, frames=slice(None)):
        config = BevoConfig()
        config.odometry.min_frame_interval, config.odometry.imu_time_offset = min_interval, offset
        odo = build_odometry(config, FUSED, camera=camera)
        idx = np.arange(len(d.frame_stamps))[frames]
        steps = feed_engine(odo, d.imu_stamps + imu_shift, d.gyro, d.accel, d.frame_stamps[idx],
                            lambda k: images[idx[k]], trailing=True)
        return np.array([s.position for s in steps]), np.array([s.stamp for s in steps]), odo.counters

    thinned, stamps, counters = run(min_interval=0.09)
    every_third, third_stamps, _ = run(frames=slice(None, None, 3))
    from bevo_ros.core.frame_clock import fast_camera_note

    config = BevoConfig()
    odo = build_odometry(config, FUSED, camera=camera)
    feed_engine(odo, d.imu_stamps, d.gyro, d.accel, d.frame_stamps, lambda k: images[k], trailing=True)
    assert "set odometry.min_frame_interval" in fast_camera_note(odo.frame_period, odo.min_frame_interval)  # 33 ms
    assert fast_camera_note(odo.frame_period, 0.09) is None and fast_camera_note(0.104, 0.0) is None  # KITTI's
    assert np.array_equal(stamps, third_stamps) and len(stamps) == len(range(0, len(d.frame_stamps), 3))
    assert counters.skipped_frame_rate == len(d.frame_stamps) - len(stamps)
    np.testing.assert_allclose(thinned, every_third, atol=1e-9)
    aligned, _, _ = run()
    corrected, _, _ = run(offset=-0.012, imu_shift=0.012)
    uncorrected, _, _ = run(imu_shift=0.012)  # its first frame has no IMU before it: dropped
    np.testing.assert_allclose(corrected, aligned, atol=1e-6)
    assert len(uncorrected) == len(aligned) - 1
    assert np.abs((uncorrected - uncorrected[0]) - (aligned[1:] - aligned[1])).max() > 1e-3
