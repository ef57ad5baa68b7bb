"""Road tilt separation: recovers fast attitude under constant camber; stateful == functional."""
from __future__ import annotations

import math

import pytest
import torch

from bevo_ros.core.road_tilt import RoadTiltFilter, lowpass_gain, road_relative_attitude

DEG = math.pi / 180.0


def cambered_drive(seconds: float = 60.0, rate: float = 100.0, seed: int = 0):
    """Gravity-referenced attitude = constant road tilt (slope 1.5 deg, camber 2.6 deg) + the
    vehicle's own fast motion (~1 Hz oscillation, 1-2 deg) + a little noise. ``(1, T, 2)`` each."""
    gen = torch.Generator().manual_seed(seed)
    t = torch.arange(int(seconds * rate), dtype=torch.float64) / rate
    own_pitch = 1.5 * DEG * torch.sin(2 * math.pi * 1.1 * t)
    own_roll = 2.0 * DEG * torch.sin(2 * math.pi * 0.8 * t + 0.3)
    own = torch.stack([own_pitch, own_roll], -1)
    own = own + 0.05 * DEG * torch.randn(own.shape, generator=gen, dtype=torch.float64)
    road = torch.tensor([1.5 * DEG, 2.6 * DEG], dtype=torch.float64)
    dt = torch.full((1, t.numel()), 1.0 / rate, dtype=torch.float64)
    return (own + road)[None], own[None], dt, t


def test_recovers_fast_attitude_under_constant_camber():
    x, own, dt, t = cambered_drive()
    tau = 5.0
    rel = road_relative_attitude(x, dt, tau)
    settle = t >= 5 * tau  # the initial tilt (sample 0 includes some of the vehicle's own motion) decays as exp(-t/tau)
    err = torch.sqrt(((rel - own)[0, settle] ** 2).mean(0)) / DEG
    raw = torch.sqrt(((x - own)[0, settle] ** 2).mean(0)) / DEG
    amp = torch.sqrt((own[0, settle] ** 2).mean(0)) / DEG
    print(
        f"\n[camber 2.6 deg, slope 1.5 deg, tau {tau} s] after {5 * tau:.0f} s: RMSE pitch/roll deg "
        f"road-relative {err.numpy().round(4)}, gravity-referenced {raw.numpy().round(4)} "
        f"(signal RMS {amp.numpy().round(3)})"
    )
    assert torch.all(err < 0.1)  # the ~1 Hz motion passes through (a 5 s low-pass barely sees it)
    assert torch.all(err * 10 < raw)


def test_tracks_a_change_of_camber_with_tau():
    # Camber steps from 0 to 3 deg at t = 10 s: the error decays as exp(-(t - 10) / tau).
    t = torch.arange(0, 40, 0.1, dtype=torch.float64)
    x = torch.zeros(1, t.numel(), 2, dtype=torch.float64)
    x[0, t >= 10, 1] = 3 * DEG
    rel = road_relative_attitude(x, torch.full((1, t.numel()), 0.1, dtype=torch.float64), 4.0)
    after = t >= 10
    expected = 3 * DEG * torch.exp(-(t[after] - 10 + 0.1) / 4.0)  # the step sample itself is already filtered once
    print(
        f"\n[camber step 3 deg, tau 4 s] residual roll 4 s after the step: {rel[0, after][40, 1].item() / DEG:.4f} deg "
        f"(3 exp(-4.1 / 4) = {3 * math.exp(-4.1 / 4):.4f})"
    )
    torch.testing.assert_close(rel[0, after, 1], expected, rtol=1e-9, atol=1e-12)


def test_streaming_equals_functional_and_irregular_dt():
    x, _, _, _ = cambered_drive(seconds=5.0, seed=1)
    x = torch.cat([x, x.flip(1) * 0.5])  # B = 2
    gen = torch.Generator().manual_seed(2)
    dt = 0.002 + 0.05 * torch.rand(x.shape[:2], generator=gen, dtype=torch.float64)
    dt[:, 7] = 0.0  # duplicated stamp: allowed, nothing changes
    tau = 2.5
    functional = road_relative_attitude(x, dt, tau)
    stamps = 1000.0 + torch.cumsum(dt, 1)
    diffs = []
    for b in range(2):  # the streaming filter follows one vehicle, in floats
        f = RoadTiltFilter(tau)
        out = torch.tensor([f.update(float(stamps[b, i]), *x[b, i].tolist()) for i in range(x.shape[1])],
                           dtype=torch.float64)
        diffs.append((out - functional[b]).abs().max().item())
        torch.testing.assert_close(torch.tensor(f.tilt, dtype=torch.float64), x[b, -1] - functional[b, -1])
    print(f"\n[streaming vs functional, 2 x T={x.shape[1]}] max diff {max(diffs):.1e} rad")
    assert max(diffs) < 1e-12  # stamp differences round dt by ~1e-13 s
    assert torch.all(functional[:, 0] == 0)


def test_gradients_flow():
    x, _, dt, _ = cambered_drive(seconds=3.0)
    x = x.clone().requires_grad_()
    tau = torch.tensor(2.0, dtype=torch.float64, requires_grad=True)
    rel = road_relative_attitude(x, dt, tau)
    gx, gtau = torch.autograd.grad(rel[0, -1, 1], (x, tau))
    print(
        f"\n[gradients] d rel_T / d x_T = {gx[0, -1, 1].item():.4f}, "
        f"d rel_T / d x_0 = {gx[0, 0, 1].item():.2e}, d rel_T / d tau = {gtau.item():.2e}"
    )
    assert gx[0, -1, 1] > 0.99 and gx[0, 0, 1] < 0 and gtau.abs() > 0
    # gradcheck on a short sequence through both inputs (float64).
    xs = x.detach()[:, :20].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: road_relative_attitude(a, dt[:, :20] * 10, b), (xs, tau))


def test_disabled():
    x, _, dt, _ = cambered_drive(seconds=1.0)
    for off in (0.0, -1.0, math.inf, None):
        assert torch.equal(road_relative_attitude(x, dt, off), x)
        f = RoadTiltFilter(off)
        assert not f.enabled
        assert f.update(0.0, *x[0, 0].tolist()) == tuple(x[0, 0].tolist())
        assert f.tilt == (0.0, 0.0)
    assert lowpass_gain(torch.tensor(1e-9), 10.0).item() == pytest.approx(1e-10, rel=1e-6)


def test_bad_input_raises():
    x, _, dt, _ = cambered_drive(seconds=1.0)
    with pytest.raises(ValueError, match="NaN"):
        RoadTiltFilter(float("nan"))
    with pytest.raises(ValueError, match=r"pitch_roll must be a tensor of shape \(B, T, 2\)"):
        road_relative_attitude(x[0], dt, 5.0)
    with pytest.raises(ValueError, match="dt must be >= 0"):
        road_relative_attitude(x, -dt, 5.0)
    bad = x.clone()
    bad[0, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        road_relative_attitude(bad, dt, 5.0)
    f = RoadTiltFilter(5.0)
    f.update(10.0, *x[0, 0].tolist())
    with pytest.raises(ValueError, match="time ran backwards"):
        f.update(9.0, *x[0, 1].tolist())
    with pytest.raises(ValueError, match="finite"):
        f.update(11.0, float("nan"), 0.0)
    f.reset()
    assert f.tilt is None
    assert f.update(11.0, *x[0, 2].tolist()) == (0.0, 0.0)  # the first sample is the tilt
