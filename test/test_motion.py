"""core.motion: round trip, Jacobian, sign conventions end to end, and one VIO step on rendered frames."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bevo_ros.datasets import synthetic as syn
from bevo_ros.core.bev import project_to_bev
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.motion import (
    motion_covariance_from_registration,
    motion_jacobian,
    pitch_scale_sensitivity,
    registration_from_vehicle_motion,
    registration_shift_floats,
    roll_yaw_sensitivity,
    vehicle_motion_from_registration,
)
from bevo_ros.core.phase_correlation import DpcConfig, register

SPEC = BevSpec()


def compose(pose: np.ndarray, motion: np.ndarray) -> np.ndarray:
    x, y, yaw = pose
    dx, dy, dyaw = motion
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([x + c * dx - s * dy, y + s * dx + c * dy, yaw + dyaw])


def test_round_trip():
    g = torch.Generator().manual_seed(0)
    motion = torch.stack([torch.rand(64, generator=g, dtype=torch.float64) * 3 - 0.5,
                          torch.randn(64, generator=g, dtype=torch.float64) * 0.3,
                          torch.randn(64, generator=g, dtype=torch.float64) * 0.1], dim=-1)
    for spec in (SPEC, BevSpec(size=64, metres_per_pixel=0.2, forward_offset=3.0)):
        angle, shift = registration_from_vehicle_motion(motion, spec)
        back = vehicle_motion_from_registration(angle, shift, spec)
        err = float((back - motion).abs().max())
        print(f"\n{spec}: round-trip max error {err:.2e}")
        assert err < 1e-12
    # Straight ahead by exactly one pixel of ground = one pixel of shift down the image.
    one_px = torch.tensor([[SPEC.metres_per_pixel, 0.0, 0.0]], dtype=torch.float64)
    a, s = registration_from_vehicle_motion(one_px, SPEC)
    assert torch.allclose(s, torch.tensor([[1.0, 0.0]], dtype=torch.float64)) and float(a) == 0.0


def test_registration_shift_floats_equals_the_tensor_form():
    """The engine's per-frame prior in floats is registration_from_vehicle_motion's shift."""
    g = np.random.default_rng(4)
    for dx, dy, dyaw in [(0.0, 0.0, 0.0), (1.3, -0.02, 0.01), (-0.4, 0.1, -0.2)] + list(g.normal(0, 1, (20, 3))):
        _, shift = registration_from_vehicle_motion(torch.tensor([[dx, dy, dyaw]], dtype=torch.float64), SPEC)
        got = registration_shift_floats(float(dx), float(dy), float(dyaw), SPEC)
        np.testing.assert_allclose(got, shift[0].tolist(), rtol=0, atol=1e-10)


def test_pure_yaw_shifts_the_bev_sideways():
    """A yaw about the base (far behind the BEV centre) also moves the BEV content sideways."""
    turn = torch.tensor([[0.0, 0.0, math.radians(2.0)]], dtype=torch.float64)
    angle, shift = registration_from_vehicle_motion(turn, SPEC)
    cx = SPEC.centre[0]
    print(f"\n2 deg left turn in place: angle {math.degrees(float(angle)):.3f} deg, shift {shift.tolist()} px "
          f"(lever {cx:.1f} m)")
    assert math.isclose(math.degrees(float(angle)), -2.0, abs_tol=1e-12)
    # The centre ground point moves right in the vehicle frame (y < 0 -> larger column).
    assert float(shift[0, 1]) > 0
    assert math.isclose(float(shift[0, 1]), cx * math.sin(math.radians(2.0)) / SPEC.metres_per_pixel, rel_tol=1e-9)


def test_jacobian_matches_autograd_and_covariance_is_psd():
    angle = torch.tensor([0.03, -0.2], dtype=torch.float64)
    shift = torch.tensor([[10.0, 1.0], [-2.0, 3.0]], dtype=torch.float64)
    J = motion_jacobian(angle, SPEC)
    for i in range(2):
        f = lambda x: vehicle_motion_from_registration(x[:1], x[1:][None], SPEC)[0]  # noqa: E731
        Ja = torch.autograd.functional.jacobian(f, torch.cat([angle[i : i + 1], shift[i]]))
        assert torch.allclose(J[i], Ja, atol=1e-12)

    class Reg:  # duck-typed Registration
        pass

    reg = Reg()
    reg.angle, reg.shift = angle, shift
    reg.angle_std = torch.tensor([0.001, 0.002], dtype=torch.float64)
    reg.shift_cov = torch.tensor([[[0.1, 0.02], [0.02, 0.2]], [[0.3, 0.0], [0.0, 0.1]]], dtype=torch.float64)
    cov = motion_covariance_from_registration(reg, SPEC)
    ev = torch.linalg.eigvalsh(cov)
    print(f"\nmotion covariance eigenvalues {ev.tolist()}")
    assert cov.shape == (2, 3, 3) and bool((ev > 0).all())
    assert torch.allclose(cov, cov.transpose(-1, -2))


@pytest.mark.parametrize(
    "motion",
    [(1.0, 0.0, 0.0), (0.0, 0.3, 0.0), (0.0, -0.3, 0.0), (0.5, 0.0, 2.0), (0.5, 0.0, -2.0), (1.2, -0.1, -1.5),
     (1.1, 0.05, 0.9)],
)
def test_signs_end_to_end_on_true_ground(motion):
    """Exact ground BEVs of two poses -> register -> motion == the true (dx, dy, dyaw)."""
    ground = syn.default_ground(0)
    m = np.array([motion[0], motion[1], math.radians(motion[2])])
    p0 = np.array([5.0, 2.0, 0.4])
    p1 = compose(p0, m)
    b0 = syn.ground_patch(p0[0], p0[1], p0[2], SPEC, ground, supersample=3, dtype=torch.float64)
    b1 = syn.ground_patch(p1[0], p1[1], p1[2], SPEC, ground, supersample=3, dtype=torch.float64)
    ones = torch.ones(1, 1, SPEC.size, SPEC.size, dtype=torch.float64)
    reg = register(b0[None, None], b1[None, None], ones, ones, DpcConfig())
    est = vehicle_motion_from_registration(reg.angle, reg.shift, SPEC)[0].numpy()
    et = float(np.linalg.norm(est[:2] - m[:2]))
    ey = math.degrees(abs(est[2] - m[2]))
    print(f"\ntrue ({m[0]:+.3f}, {m[1]:+.3f}, {math.degrees(m[2]):+.3f} deg) est ({est[0]:+.3f}, {est[1]:+.3f}, "
          f"{math.degrees(est[2]):+.3f} deg): err {et * 100:.2f} cm, {ey:.3f} deg, quality {float(reg.quality):.3f}")
    assert et < 0.03 and ey < 0.3


@pytest.fixture(scope="module")
def rendered_drive():
    """A turning synthetic drive (~1 m/frame), 4 rendered frames."""
    drive = syn.make_drive(seed=7, duration=0.3, render=True)
    return drive


def test_one_vio_step_on_rendered_frames(rendered_drive):
    """BEVs from rendered frames with the true road-relative attitude -> DPC -> motion == truth."""
    d = rendered_drive
    cam = d.camera.to(dtype=torch.float32)
    imgs = torch.from_numpy(np.asarray(d.images)).float()[:, None] / 255.0
    pr = torch.from_numpy(d.pitch_roll_road).float()
    bev, mask = project_to_bev(imgs, cam, pr[:, 0], pr[:, 1], SPEC)
    reg = register(bev[:-1], bev[1:], mask[:-1], mask[1:], DpcConfig())
    est = vehicle_motion_from_registration(reg.angle.double(), reg.shift.double(), SPEC).numpy()
    gt = d.relative_motion
    et = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    ey = np.degrees(np.abs(est[:, 2] - gt[:, 2]))
    for i in range(len(gt)):
        print(f"\npair {i}: true ({gt[i, 0]:.4f}, {gt[i, 1]:+.4f}, {math.degrees(gt[i, 2]):+.3f} deg) "
              f"est ({est[i, 0]:.4f}, {est[i, 1]:+.4f}, {math.degrees(est[i, 2]):+.3f} deg) "
              f"err {et[i] * 100:.2f} cm {ey[i]:.3f} deg q {float(reg.quality[i]):.3f}", end="")
    print(f"\ntranslation err mean {et.mean() * 100:.2f} max {et.max() * 100:.2f} cm; yaw err mean {ey.mean():.3f} "
          f"max {ey.max():.3f} deg")
    assert ey.max() <= 0.3
    assert et.mean() <= 0.03 and et.max() <= 0.05


def test_bad_input_raises():
    with pytest.raises(ValueError, match="angle"):
        vehicle_motion_from_registration(torch.zeros(2), torch.zeros(3, 2), SPEC)
    with pytest.raises(ValueError, match="motion must be"):
        registration_from_vehicle_motion(torch.zeros(2, 2), SPEC)


def test_attitude_sensitivities_match_reprojection():
    """A pitch error d scales the BEV's forward motion by 1 + k_p d (k_p = 2 X / h); a roll error
    shears it into a yaw error of about dx d / (2 h), and about the BEV centre a lateral one,
    d(dy) = -C_x d(dyaw). Re-project rendered frames of a smooth drive with the true attitude
    +- 0.01 rad and measure all three."""
    from bevo_ros.core.sequence import project_frames, register_consecutive

    d = syn.make_drive(seed=4, duration=1.0, bumps=0.0, render="lazy")
    images = torch.as_tensor(np.stack([np.asarray(d.image(i)) for i in range(len(d.frame_stamps))]))
    road = torch.as_tensor(d.pitch_roll_road, dtype=torch.float32)
    spec = BevSpec()

    def motion(delta: tuple[float, float]) -> torch.Tensor:
        bev, mask = project_frames(images, d.camera, road + torch.tensor(delta), spec)
        reg = register_consecutive(bev, mask, DpcConfig())
        return vehicle_motion_from_registration(reg.angle, reg.shift, spec).double()

    m0 = motion((0.0, 0.0))
    per_pitch = (motion((0.01, 0.0)) - motion((-0.01, 0.0))) / 0.02 / m0[:, :1]  # per rad, per metre of dx
    per_roll = (motion((0.0, 0.01)) - motion((0.0, -0.01))) / 0.02 / m0[:, :1]
    k_p = pitch_scale_sensitivity(spec, float(d.camera.T_base_cam[0, 3]), d.camera.mount_height)
    k_r = roll_yaw_sensitivity(d.camera.mount_height)
    pitch_dx, roll_yaw, roll_dy = (float(v) for v in (per_pitch[:, 0].mean(), per_roll[:, 2].mean(),
                                                       per_roll[:, 1].mean()))
    print(f"\nper rad and metre: d(dx)/dpitch {pitch_dx:.2f} (model -{k_p:.2f}); d(dyaw)/droll {roll_yaw:.3f} "
          f"(model -{k_r:.3f}); d(dy)/droll {roll_dy:.2f} (model C_x k_r = {spec.centre[0] * k_r:.2f})")
    assert pitch_dx == pytest.approx(-k_p, rel=0.1)  # positive pitch (nose down) shrinks the motion
    assert -1.1 * k_r < roll_yaw < -0.5 * k_r  # at most the isotropic-texture value: conservative
    assert roll_dy == pytest.approx(-spec.centre[0] * roll_yaw, rel=0.2)
    with pytest.raises(ValueError):
        pitch_scale_sensitivity(spec, 100.0, 1.65)
    with pytest.raises(ValueError):
        roll_yaw_sensitivity(0.0)
