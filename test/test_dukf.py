"""DUKF: equality with filterpy, gradients, denoising on synthetic and real IMU data, bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bevo_ros.core.dukf import DUKF, DukfState, accel_to_pitch_roll, merwe_weights, steady_state_variance
from bevo_ros.core.geometry import rotation_from_rpy
from helpers.env import in_ci

G = 9.80665
DEG = math.pi / 180.0


def rmse_deg(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray) -> np.ndarray:
    """Per-column RMSE in degrees of ``(..., 2)`` angle arrays in radians."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return np.degrees(np.sqrt((d.reshape(-1, d.shape[-1]) ** 2).mean(0)))


def gravity_in_body(pitch: torch.Tensor, roll: torch.Tensor) -> torch.Tensor:
    """Specific force of a resting IMU, ``R^T [0, 0, g]`` with R from geometry.py. -> ``(..., 3)``."""
    rot = rotation_from_rpy(roll, pitch, torch.zeros_like(pitch))
    return G * rot[..., 2, :]  # row 2 of R = R^T e_z


# ---------------------------------------------------------------------------------- signs


def test_accel_to_pitch_roll_inverts_gravity_rep103():
    gen = torch.Generator().manual_seed(0)
    pitch = (torch.rand(500, generator=gen, dtype=torch.float64) - 0.5) * 2.8  # within +-80 deg
    roll = (torch.rand(500, generator=gen, dtype=torch.float64) - 0.5) * 6.0  # within +-172 deg
    yaw = (torch.rand(500, generator=gen, dtype=torch.float64) - 0.5) * 6.0
    accel = G * rotation_from_rpy(roll, pitch, yaw)[..., 2, :]  # yaw must not matter
    est = accel_to_pitch_roll(accel)
    err = (est - torch.stack([pitch, roll], -1)).abs().max().item()
    print(f"\n[signs] max |accel angles - truth| over 500 attitudes: {err:.2e} rad")
    assert err < 1e-12
    # REP-103: nose down (positive pitch) -> the resting accelerometer reads ax = -g sin(pitch).
    nose_down = gravity_in_body(torch.tensor([0.2], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64))
    assert nose_down[0, 0] == pytest.approx(-G * math.sin(0.2))
    left_up = gravity_in_body(torch.tensor([0.0], dtype=torch.float64), torch.tensor([0.1], dtype=torch.float64))
    assert left_up[0, 1] == pytest.approx(G * math.sin(0.1))
    assert accel_to_pitch_roll(nose_down)[0, 0].item() == pytest.approx(0.2)
    assert accel_to_pitch_roll(left_up)[0, 1].item() == pytest.approx(0.1)


# ------------------------------------------------------------------------- filterpy equality


def _np_euler_fx(x, dt, w):
    pitch, roll = x
    wx, wy, wz = w
    return np.array(
        [
            pitch + (wy * math.cos(roll) - wz * math.sin(roll)) * dt,
            roll + (wx + (wy * math.sin(roll) + wz * math.cos(roll)) * math.tan(pitch)) * dt,
        ]
    )


def _np_additive_fx(x, dt, w):
    return np.array([x[0] + w[1] * dt, x[1] + w[0] * dt])


def _np_accel_angles(a):
    return np.array([-math.atan2(a[0], math.hypot(a[1], a[2])), math.atan2(a[1], a[2])])


@pytest.mark.parametrize("motion_model", ["euler", "additive"])
def test_matches_filterpy(motion_model):
    if not in_ci():  # a test requirement (requirements.txt); colcon test on a Jazzy install may lack it
        pytest.importorskip("filterpy", reason="filterpy (requirements.txt) not installed: make setup")
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    rng = np.random.default_rng(1)
    steps, batch = 300, 2
    o, q = np.array([2e-3, 1e-3]), np.array([3e-3, 5e-3])
    dukf = DUKF(process_var=o, measurement_var=q, motion_model=motion_model, jitter=0.0).double()
    o, q = dukf.process_var.detach().numpy(), dukf.measurement_var.detach().numpy()  # float32-stored
    # An attitude random walk up to ~+-0.5 rad (the Euler model's nonlinearity matters), fast
    # rates, strong yaw rate, noisy accelerometer and irregular dt.
    gyro = rng.normal(0.0, 0.5, (batch, steps, 3))
    gyro[..., 2] += 1.0
    dt = rng.uniform(0.002, 0.05, (batch, steps))
    att = np.cumsum(rng.normal(0.0, 0.03, (batch, steps, 2)), axis=1).clip(-0.5, 0.5)
    accel = gravity_in_body(torch.from_numpy(att[..., 0]), torch.from_numpy(att[..., 1])).numpy()
    accel += rng.normal(0.0, 0.5, accel.shape)
    x0 = rng.normal(0.0, 0.2, (batch, 2))
    p0 = np.array([[[0.02, 0.004], [0.004, 0.03]]] * batch)

    state = DukfState(torch.from_numpy(x0), torch.from_numpy(p0))
    with torch.no_grad():
        means, covs, _ = dukf.filter(torch.from_numpy(gyro), torch.from_numpy(accel), torch.from_numpy(dt), state)

    fx = _np_euler_fx if motion_model == "euler" else _np_additive_fx
    worst_mean = worst_cov = 0.0
    for b in range(batch):
        points = MerweScaledSigmaPoints(2, alpha=dukf.alpha, beta=dukf.beta, kappa=dukf.kappa)
        ukf = UnscentedKalmanFilter(dim_x=2, dim_z=2, dt=0.01, hx=lambda x: x, fx=fx, points=points)
        ukf.x, ukf.P, ukf.R = x0[b].copy(), p0[b].copy(), np.diag(q)
        for t in range(steps):
            ukf.Q = np.diag(o) * dt[b, t]
            ukf.predict(dt=dt[b, t], w=gyro[b, t])
            ukf.update(_np_accel_angles(accel[b, t]))
            worst_mean = max(worst_mean, np.abs(ukf.x - means[b, t].numpy()).max())
            worst_cov = max(worst_cov, np.abs(ukf.P - covs[b, t].numpy()).max() / np.abs(ukf.P).max())
    spread = np.degrees(means[..., 0].max().item() - means[..., 0].min().item())
    print(
        f"\n[filterpy {motion_model}] {batch}x{steps} steps, pitch spans {spread:.1f} deg: "
        f"max |mean diff| {worst_mean:.2e} rad, max relative |cov diff| {worst_cov:.2e}"
    )
    assert worst_mean < 1e-9
    assert worst_cov < 1e-9


def test_weights_match_filterpy_for_defaults():
    from filterpy.kalman import MerweScaledSigmaPoints

    f = DUKF()
    ref = MerweScaledSigmaPoints(2, alpha=f.alpha, beta=f.beta, kappa=f.kappa)
    lam, wm, wc = merwe_weights(2, f.alpha, f.beta, f.kappa)
    print(f"\n[weights] alpha={f.alpha} beta={f.beta} kappa={f.kappa}: lambda={lam}, wm={wm}, wc={wc}")
    np.testing.assert_allclose(wm, ref.Wm, rtol=0, atol=1e-15)
    np.testing.assert_allclose(wc, ref.Wc, rtol=0, atol=1e-15)
    assert min(wm) >= 0 and min(wc) >= 0  # the float32-safety argument for the defaults


# ------------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("motion_model", ["euler", "additive"])
def test_gradcheck_noise_parameters(motion_model):
    dukf = DUKF(process_var=(3e-3, 2e-3), measurement_var=(4e-3, 6e-3), motion_model=motion_model).double()
    gen = torch.Generator().manual_seed(3)
    b, t = 2, 5
    gyro = torch.randn(b, t, 3, generator=gen, dtype=torch.float64) * 0.5
    accel = gravity_in_body(*(torch.randn(2, b, t, generator=gen, dtype=torch.float64) * 0.1))
    accel = accel + torch.randn(b, t, 3, generator=gen, dtype=torch.float64) * 0.5
    dt = torch.full((b, t), 0.05, dtype=torch.float64)

    def run(log_o: torch.Tensor, log_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        params = {"log_process_var": log_o, "log_measurement_var": log_q}
        mean, cov, _ = torch.func.functional_call(dukf, params, (gyro, accel, dt))
        return mean, cov

    log_o = dukf.log_process_var.detach().clone().requires_grad_()
    log_q = dukf.log_measurement_var.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(run, (log_o, log_q), eps=1e-6, atol=1e-8, rtol=1e-5)
    # And the gradient is not trivially zero: the last pitch depends on both O and Q.
    mean, _ = run(log_o, log_q)
    g_o, g_q = torch.autograd.grad(mean[:, -1, 0].sum(), (log_o, log_q))
    print(f"\n[gradcheck {motion_model}] d pitch_T / d log O = {g_o.tolist()}, d / d log Q = {g_q.tolist()}")
    assert g_o[0].abs() > 1e-6 and g_q[0].abs() > 1e-6
    assert [n for n, _ in dukf.named_parameters()] == ["log_process_var", "log_measurement_var"]


# ----------------------------------------------------------------------- synthetic IMU drives


def synthetic_imu(
    seconds: float = 20.0,
    rate: float = 100.0,
    yaw_rate: float = 0.0,
    roll_offset: float = 0.0,
    amplitude: float = 3.0 * DEG,
    vibration: float = 0.8,
    gyro_noise: float = 0.01,
    gyro_bias: tuple[float, float, float] = (0.003, -0.002, 0.001),
    seed: int = 0,
) -> dict[str, torch.Tensor]:
    """IMU of a vehicle pitching/rolling a few degrees at ~1 Hz, optionally turning.

    Truth is smooth analytic pitch/roll/yaw; the gyro gets the exact Z-Y-X body rates + bias +
    white noise, the accelerometer gravity in the body frame + vibration (no centripetal term).
    Returns float64 tensors with a batch dim of 1.
    """
    gen = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate)) / rate
    w1, w2 = 2 * math.pi * 1.0, 2 * math.pi * 0.7
    pitch = amplitude * np.sin(w1 * t) + 0.5 * amplitude * np.sin(0.3 * w1 * t + 1.0)
    roll = roll_offset + amplitude * np.sin(w2 * t + 0.5)
    dpitch = amplitude * w1 * np.cos(w1 * t) + 0.5 * amplitude * 0.3 * w1 * np.cos(0.3 * w1 * t + 1.0)
    droll = amplitude * w2 * np.cos(w2 * t + 0.5)
    dyaw = np.full_like(t, yaw_rate)
    # Inverse of the Z-Y-X kinematics: body rates from Euler-angle rates.
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    wx = droll - dyaw * sp
    wy = dpitch * cr + dyaw * sr * cp
    wz = -dpitch * sr + dyaw * cr * cp
    gyro = np.stack([wx, wy, wz], -1) + np.asarray(gyro_bias) + gen.normal(0, gyro_noise, (t.size, 3))
    accel = gravity_in_body(torch.from_numpy(pitch), torch.from_numpy(roll)).numpy()
    accel = accel + gen.normal(0, vibration, accel.shape)
    as_t = lambda a: torch.from_numpy(np.ascontiguousarray(a))[None]  # noqa: E731
    return {
        "gyro": as_t(gyro),
        "accel": as_t(accel),
        "dt": as_t(np.full(t.size, 1.0 / rate)),
        "truth": as_t(np.stack([pitch, roll], -1)),
    }


# O: the gyro's angle random walk (0.01 rad/s at 100 Hz -> 1e-6 rad^2/s) plus room for its
# bias; Q: the vibration's angle noise, (0.8 / 9.81)^2 ~ 7e-3 rad^2.
SYNTH_O, SYNTH_Q = (1e-4, 1e-4), (7e-3, 7e-3)


def test_denoises_vibrating_accelerometer():
    d = synthetic_imu()
    dukf = DUKF(process_var=SYNTH_O, measurement_var=SYNTH_Q)
    with torch.no_grad():
        mean, _, _ = dukf.filter(d["gyro"].float(), d["accel"].float(), d["dt"].float())
    skip = 200  # 2 s to settle from the first (noisy) accelerometer sample
    raw = rmse_deg(accel_to_pitch_roll(d["accel"])[0, skip:], d["truth"][0, skip:])
    filt = rmse_deg(mean[0, skip:], d["truth"][0, skip:])
    print(f"\n[synthetic 100 Hz, vibration 0.8 m/s^2] RMSE pitch/roll deg: raw {raw.round(3)}, DUKF {filt.round(3)}")
    assert np.all(filt * 2 <= raw)


def test_euler_beats_additive_when_turning_with_roll():
    # A long bend: 0.3 rad/s yaw rate with 4 deg of roll; wz sin(roll) leaks ~1.2 deg/s into pitch.
    d = synthetic_imu(yaw_rate=0.3, roll_offset=4 * DEG, seed=5)
    errs = {}
    for model in ("euler", "additive"):
        dukf = DUKF(process_var=SYNTH_O, measurement_var=SYNTH_Q, motion_model=model)
        with torch.no_grad():
            mean, _, _ = dukf.filter(d["gyro"], d["accel"], d["dt"])
        errs[model] = rmse_deg(mean[0, 200:], d["truth"][0, 200:])
    print(
        f"\n[turning, roll 4 deg, 0.3 rad/s] RMSE pitch/roll deg: "
        f"euler {errs['euler'].round(3)}, additive {errs['additive'].round(3)}"
    )
    assert errs["euler"][0] * 1.5 < errs["additive"][0]
    assert errs["euler"][1] <= errs["additive"][1] * 1.05


def test_process_noise_is_rate_independent():
    # O is a density: predicting 1 s costs O * 1 s of variance whatever the IMU rate.
    dukf = DUKF(process_var=(2e-3, 5e-4), motion_model="additive", jitter=0.0).double()
    got = []
    for rate in (10, 100, 400):
        state = dukf.init_state(pitch_roll=torch.zeros(1, 2, dtype=torch.float64), var=1e-4)
        gyro, dt = torch.zeros(1, 3, dtype=torch.float64), torch.full((1,), 1.0 / rate, dtype=torch.float64)
        for _ in range(rate):
            state = dukf.predict(state, gyro, dt)
        got.append(torch.diagonal(state.cov[0]).tolist())
    print(f"\n[rate independence] variance after 1 s at 10/100/400 Hz: {got}")
    want = (1e-4 + dukf.process_var.detach()).tolist()  # the float32-stored O, exactly
    np.testing.assert_allclose(got, [want] * 3, rtol=1e-12)


def test_steady_state_variance_is_where_the_filter_settles():
    """The closed-form fixed point of the Riccati equation == the DUKF's variance after a long run
    (level, at rest), at KITTI's 10 Hz and a 100 Hz IMU, for the default and other O/Q."""
    for o, q in ((1e-6, 5e-2), (1e-4, 1e-2)):
        dukf = DUKF(process_var=(o, o), measurement_var=(q, q)).double()
        for rate in (10.0, 100.0):
            n = int(2.5 * math.sqrt(q / (o / rate)))  # 2.5 of the filter's time constants: within ~1 %
            dt = torch.full((1, n), 1.0 / rate, dtype=torch.float64)
            accel = torch.tensor([0.0, 0.0, 9.81], dtype=torch.float64).expand(1, n, 3)
            with torch.no_grad():
                _, cov, _ = dukf.filter(torch.zeros(1, n, 3, dtype=torch.float64), accel, dt)
            got = float(cov[0, -1, 0, 0])
            (o_, _), (q_, _) = dukf.noise_floats()
            want = steady_state_variance(o_, q_, 1.0 / rate)
            print(f"\n[steady state] O {o:g} Q {q:g} at {rate:g} Hz: DUKF {math.degrees(math.sqrt(got)):.4f} deg "
                  f"after {n} steps, closed form {math.degrees(math.sqrt(want)):.4f} deg")
            assert got == pytest.approx(want, rel=0.02)
    with pytest.raises(ValueError):
        steady_state_variance(0.0, 1e-2, 0.01)


def test_float32_long_run_stays_spd_and_batch_consistent():
    d = synthetic_imu(seconds=5.0, rate=400.0, seed=7)
    # Tiny process noise, huge measurement noise, tiny initial variance: the covariance sits near
    # 1e-7 rad^2 and the gain near 0, where float32 rounding could make P indefinite.
    dukf = DUKF(process_var=(1e-10, 1e-10), measurement_var=(1.0, 1.0))
    gyro = torch.cat([d["gyro"], d["gyro"].flip(1)]).float()
    accel = torch.cat([d["accel"], d["accel"].flip(1)]).float()
    dt = torch.cat([d["dt"], d["dt"]]).float()
    with torch.no_grad():
        mean, cov, _ = dukf.filter(gyro, accel, dt, dukf.init_state(accel=accel[:, 0], var=1e-9))
        single, _, _ = dukf.filter(gyro[1:], accel[1:], dt[1:], dukf.init_state(accel=accel[1:, 0], var=1e-9))
    eig = torch.linalg.eigvalsh(cov.double())
    print(
        f"\n[float32, {gyro.shape[1]} steps at 400 Hz] min cov eigenvalue {eig.min().item():.3e}, "
        f"finite: {bool(torch.isfinite(mean).all())}"
    )
    assert torch.isfinite(mean).all() and torch.isfinite(cov).all()
    assert eig.min() > 0
    assert (cov - cov.transpose(-1, -2)).abs().max() == 0
    assert torch.allclose(mean[1], single[0], atol=1e-6)


# ------------------------------------------------------------------------------- bad input


def test_bad_input_raises():
    dukf = DUKF()
    state = dukf.init_state(batch_size=2)
    g, a, dt = torch.zeros(2, 3), torch.tensor([[0.0, 0.0, G]] * 2), torch.full((2,), 0.01)
    dukf.step(state, g, a, dt)  # valid
    with pytest.raises(ValueError, match="dt must be > 0"):
        dukf.step(state, g, a, torch.tensor([0.01, 0.0]))
    with pytest.raises(ValueError, match="dt must be > 0"):
        dukf.step(state, g, a, torch.tensor([-0.01, 0.01]))
    with pytest.raises(ValueError, match="dt contains non-finite"):
        dukf.step(state, g, a, torch.tensor([float("inf"), 0.01]))
    with pytest.raises(ValueError, match="gyro contains non-finite"):
        dukf.step(state, torch.tensor([[0.0, float("nan"), 0.0], [0.0, 0.0, 0.0]]), a, dt)
    with pytest.raises(ValueError, match="accel contains non-finite"):
        dukf.step(state, g, torch.tensor([[0.0, 0.0, float("inf")], [0.0, 0.0, G]]), dt)
    with pytest.raises(ValueError, match="accel contains non-finite"):
        dukf.update(state, torch.tensor([[0.0, 0.0, float("nan")], [0.0, 0.0, G]]))
    with pytest.raises(ValueError, match="dt must be > 0"):
        dukf.predict(state, g, torch.zeros(2))
    with pytest.raises(ValueError, match=r"gyro must have shape \(2, 3\)"):
        dukf.step(state, torch.zeros(3), a, dt)
    with pytest.raises(ValueError, match=r"dt must have shape \(2,\)"):
        dukf.step(state, g, a, torch.full((2, 1), 0.01))
    with pytest.raises(ValueError, match="state must be a DukfState"):
        dukf.step((state.mean, state.cov), g, a, dt)
    with pytest.raises(ValueError, match=r"accel must have shape \(2, 4, 3\)"):
        dukf.filter(torch.zeros(2, 4, 3), torch.zeros(2, 5, 3), torch.full((2, 4), 0.01))
    with pytest.raises(ValueError, match="dt must be > 0"):
        dukf.filter(torch.zeros(1, 3, 3), a[:1, None].expand(1, 3, 3), torch.tensor([[0.01, 0.01, 0.0]]))
    with pytest.raises(ValueError, match="motion_model"):
        DUKF(motion_model="quaternion")
    with pytest.raises(ValueError, match="process_var"):
        DUKF(process_var=(1e-3, -1.0))
    with pytest.raises(ValueError, match="measurement_var"):
        DUKF(measurement_var=(1e-3, 1e-3, 1e-3))
    with pytest.raises(ValueError, match="not both"):
        dukf.init_state(accel=a, pitch_roll=torch.zeros(2, 2))
    with pytest.raises(ValueError, match="var"):
        dukf.init_state(accel=a, var=-1.0)


def test_init_state_and_noise_properties():
    dukf = DUKF(process_var=(1e-4, 2e-4), measurement_var=(3e-3, 4e-3))
    torch.testing.assert_close(dukf.process_var, torch.tensor([1e-4, 2e-4]))
    torch.testing.assert_close(dukf.measurement_var, torch.tensor([3e-3, 4e-3]))
    accel = gravity_in_body(torch.tensor([0.05, -0.1]), torch.tensor([0.02, 0.03]))
    s = dukf.init_state(accel=accel)
    torch.testing.assert_close(s.mean, torch.tensor([[0.05, 0.02], [-0.1, 0.03]]))
    torch.testing.assert_close(s.cov, torch.diag_embed(torch.tensor([[3e-3, 4e-3]] * 2)))
    s = dukf.init_state(pitch_roll=torch.zeros(3, 2, dtype=torch.float64), var=(1e-2, 2e-2))
    assert s.mean.dtype == torch.float64 and s.cov.shape == (3, 2, 2)
    assert dukf.init_state(batch_size=4).mean.shape == (4, 2)
    # filter() with no state: sample 0 initialises, its dt is unused.
    mean, cov, last = dukf.filter(torch.zeros(2, 1, 3), accel[:, None], torch.full((2, 1), float("nan")))
    torch.testing.assert_close(mean[:, 0], dukf.init_state(accel=accel).mean)
    assert last.mean.shape == (2, 2)


# --------------------------------------------------------------------------------- real OXTS


@pytest.mark.kitti
def test_kitti_oxts_filtered_closer_than_raw(kitti_root):
    from bevo_ros.datasets.kitti import read_oxts  # here: a reader problem must not hide the other DUKF tests

    oxts = kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0020_sync" / "oxts"
    record = read_oxts(oxts)
    rows, stamps_ns = record.data, record.stamps_ns
    assert rows.shape == (1104, 30) and stamps_ns.shape == (1104,)
    dt = np.diff(stamps_ns, prepend=stamps_ns[0]) * 1e-9  # exact integer differences, then seconds
    stamps = record.stamps
    gyro = torch.from_numpy(rows[None, :, 17:20])  # wx, wy, wz
    accel = torch.from_numpy(rows[None, :, 11:14])  # ax, ay, az
    ref = rows[:, [4, 3]]  # the unit's own (pitch, roll)
    dukf = DUKF()  # defaults: grid-searched on other drives (see dukf.py), not on this one
    with torch.no_grad():
        mean, _, _ = dukf.filter(gyro, accel, torch.from_numpy(dt)[None])
        additive, _, _ = DUKF(motion_model="additive").filter(gyro, accel, torch.from_numpy(dt)[None])
    raw = rmse_deg(accel_to_pitch_roll(accel)[0], ref)
    filt = rmse_deg(mean[0], ref)
    add = rmse_deg(additive[0], ref)
    print(
        f"\n[KITTI 2011_09_30_drive_0020 OXTS, {len(stamps)} samples at {1 / np.median(dt[1:]):.1f} Hz] "
        f"RMSE pitch/roll deg vs the unit's own: raw accel {raw.round(3)}, DUKF euler {filt.round(3)}, "
        f"DUKF additive {add.round(3)}"
    )
    assert np.all(filt < raw)
    assert np.all(filt * 2 < raw)  # margin: a real filter, not a lucky draw


@pytest.mark.parametrize("motion_model", ["euler", "additive"])
def test_scalar_inference_path_equals_the_tensor_path(motion_model):
    """DUKF.step_scalar (the engine's per-message path) is the tensor step to rounding."""
    import random

    f = DUKF(1e-4, 1e-2, motion_model=motion_model).double()
    state = f.init_state(accel=torch.tensor([[0.3, 0.5, 9.7]], dtype=torch.float64))
    mean = tuple(state.mean[0].tolist())
    cov = (state.cov[0, 0, 0].item(), state.cov[0, 0, 1].item(), state.cov[0, 1, 1].item())
    noise, rnd, worst = f.noise_floats(), random.Random(0), 0.0
    for _ in range(300):
        g = [rnd.uniform(-0.3, 0.3) for _ in range(3)]
        a = [rnd.uniform(-2, 2), rnd.uniform(-2, 2), 9.8 + rnd.uniform(-1, 1)]
        dt = rnd.uniform(0.002, 0.1)
        state = f.step(state, torch.tensor([g], dtype=torch.float64), torch.tensor([a], dtype=torch.float64),
                       torch.tensor([dt], dtype=torch.float64))
        mean, cov = f.step_scalar(mean, cov, g, a, dt, noise)
        ref = [*state.mean[0].tolist(), state.cov[0, 0, 0].item(), state.cov[0, 0, 1].item(), state.cov[0, 1, 1].item()]
        worst = max(worst, max(abs(x - y) for x, y in zip([*mean, *cov], ref)))
    print(f"\n[{motion_model}] scalar vs tensor step, 300 random steps: max difference {worst:.1e}")
    assert worst < 1e-12


def test_scalar_step_reports_the_accelerometer_pull():
    """``return_pull``: the same posterior, plus its difference from the gyro-only prediction
    (the engine's pitch-change correction gates on it). With an accelerometer the update cannot
    trust (huge extra variance) the pull vanishes; a tilted reading pulls towards itself."""
    f = DUKF(1e-4, 1e-2).double()
    noise = f.noise_floats()
    mean, cov = (0.0, 0.0), (1e-3, 0.0, 1e-3)
    g, dt = [0.0, 0.05, 0.0], 0.01  # 0.05 rad/s about y: the prediction moves the pitch by 5e-4 rad
    level = [0.0, 0.0, 9.81]
    plain = f.step_scalar(mean, cov, g, level, dt, noise)
    m, c, pull = f.step_scalar(mean, cov, g, level, dt, noise, return_pull=True)
    assert (m, c) == plain
    assert m[0] - pull[0] == pytest.approx(5e-4, rel=1e-3)  # the prediction, gyro only
    _, _, none = f.step_scalar(mean, cov, g, level, dt, noise, (1e12, 1e12), return_pull=True)
    assert abs(none[0]) < 1e-12 and abs(none[1]) < 1e-12
    nose_down = [-9.81 * math.sin(0.05), 0.0, 9.81 * math.cos(0.05)]  # a reading of +0.05 rad pitch
    _, _, pulled = f.step_scalar(mean, cov, [0.0, 0.0, 0.0], nose_down, dt, noise, return_pull=True)
    assert 0.0 < pulled[0] < 0.05 and abs(pulled[1]) < 1e-9


def test_scalar_step_reports_the_innovation():
    """``return_innovation``: the accelerometer's (pitch, roll) less the gyro-only prediction and the
    gain's diagonal, after the pull if both are asked for; the posterior is the same. core/gyro_bias
    learns from them."""
    f = DUKF(1e-4, 1e-2).double()
    noise = f.noise_floats()
    mean, cov, dt = (0.01, -0.02), (1e-3, 1e-4, 2e-3), 0.01
    g, accel = [0.02, 0.05, 0.1], [-9.81 * math.sin(0.05), 0.3, 9.81 * math.cos(0.05)]
    m, c, pull, (innovation, gain) = f.step_scalar(mean, cov, g, accel, dt, noise, return_pull=True,
                                                   return_innovation=True)
    assert (m, c) == f.step_scalar(mean, cov, g, accel, dt, noise)
    z = accel_to_pitch_roll(torch.tensor(accel, dtype=torch.float64)).tolist()
    predicted = (m[0] - pull[0], m[1] - pull[1])
    assert innovation == pytest.approx((z[0] - predicted[0], z[1] - predicted[1]), abs=1e-12)
    # the gain's diagonal: a pitch-only innovation moves the pitch by gain[0] times it
    _, _, pull_p, ((ep, er), gain_p) = f.step_scalar((0.0, 0.0), (cov[0], 0.0, cov[2]), [0.0] * 3, [-9.81 * math.sin(0.05), 0.0,
                                                     9.81 * math.cos(0.05)], dt, noise, return_pull=True, return_innovation=True)
    assert abs(er) < 1e-12 and pull_p[0] == pytest.approx(gain_p[0] * ep, rel=1e-9) and 0 < gain_p[0] < 1
    m2, c2, only = f.step_scalar(mean, cov, g, accel, dt, noise, return_innovation=True)
    assert (m2, c2, only) == (m, c, (innovation, gain))
