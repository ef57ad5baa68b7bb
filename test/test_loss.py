"""core.loss: Gaussian targets, KL direction and safety, gradient down to the BEV attitude."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from bevo_ros.core.loss import gaussian_target_1d, gaussian_target_2d, kl_target_predicted, registration_kl_loss
from bevo_ros.core.phase_correlation import DpcConfig, angle_bins, register, shift_bins


def test_targets_are_normalised_and_centred():
    bins = angle_bins(DpcConfig(), torch.float64)
    centre = torch.tensor([0.0, math.radians(3.3), math.radians(89.9)], dtype=torch.float64)
    t = gaussian_target_1d(centre, bins, math.radians(1.0), period=math.pi)
    assert torch.allclose(t.sum(-1), torch.ones(3, dtype=torch.float64))
    # Mean (circular for the wrapped one) equals the centre.
    mean = (t * bins).sum(-1)
    print(f"\n1-D target means {torch.rad2deg(mean[:2]).tolist()} deg; wrapped target mass at -90 deg "
          f"{float(t[2, :10].sum()):.3f}")
    assert torch.allclose(mean[:2], centre[:2], atol=1e-9)
    assert float(t[2, :10].sum()) > 0.3  # the bump near +90 continues at -90
    grid = shift_bins(100, torch.float64)
    c2 = torch.tensor([[3.25, -7.5], [49.0, 0.0]], dtype=torch.float64)
    t2 = gaussian_target_2d(c2, grid, 1.0, period=100.0)
    assert t2.shape == (2, 100, 100) and torch.allclose(t2.sum((-1, -2)), torch.ones(2, dtype=torch.float64))
    m2 = (t2[0, ..., None] * grid).sum((0, 1))
    print(f"2-D target mean {m2.tolist()}; wrapped mass at row -50: {float(t2[1, 0].sum()):.3f}")
    assert torch.allclose(m2, c2[0], atol=1e-9)
    assert float(t2[1, 0].sum()) > 0.2
    with pytest.raises(ValueError, match="sigma"):
        gaussian_target_1d(centre, bins, 0.0)
    with pytest.raises(ValueError, match="centre"):
        gaussian_target_2d(c2[0], grid, 1.0)


def test_kl_is_zero_at_the_target_and_safe():
    bins = angle_bins(DpcConfig(), torch.float64)
    t = gaussian_target_1d(torch.tensor([0.1], dtype=torch.float64), bins, 0.02)
    assert abs(float(kl_target_predicted(t, t.log()))) < 1e-12
    # A prediction with (numerically) zero mass on the target: large but finite, never nan.
    logits = torch.full((1, bins.numel()), -1e4, dtype=torch.float64)
    logits[0, 0] = 0.0
    kl = kl_target_predicted(t, F.log_softmax(logits, -1))
    print(f"\nKL of a far one-hot prediction: {float(kl):.1f}")
    assert torch.isfinite(kl) and float(kl) > 100


def test_loss_prefers_the_right_answer_and_is_nonnegative():
    A, S = 360, 100
    bins, grid = angle_bins(DpcConfig(), torch.float64), shift_bins(S, torch.float64)
    true_a, true_s = torch.tensor([0.05], dtype=torch.float64), torch.tensor([[10.0, -2.0]], dtype=torch.float64)

    def fake(a, s, width=1.5):
        rl = gaussian_target_1d(a, bins, math.radians(width), period=math.pi).clamp_min(1e-300).log()
        tl = gaussian_target_2d(s, grid, width, period=float(S)).clamp_min(1e-300).log()
        return SimpleNamespace(rotation_log_prob=rl, rotation_bins=bins, translation_log_prob=tl, translation_bins=grid)

    right = registration_kl_loss(fake(true_a, true_s), true_a, true_s)
    off = registration_kl_loss(fake(true_a + 0.01, true_s + 2.0), true_a, true_s)
    print(f"\nloss right {float(right):.4f}, off {float(off):.4f}")
    assert 0.0 <= float(right) < float(off)


def test_gradient_reaches_the_attitude():
    """KL loss -> DPC -> BEV projection -> pitch: finite, non-zero, matches finite differences."""
    from bevo_ros.datasets import synthetic as syn
    from bevo_ros.core.bev import project_to_bev
    from bevo_ros.core.geometry import BevSpec, CameraModel
    from bevo_ros.core.motion import registration_from_vehicle_motion

    spec = BevSpec()
    cam = syn.kitti_like_camera(dtype=torch.float64)
    K = cam.K.clone()
    K[:2] /= 4  # quarter resolution: a fast smooth test image
    K[:2, 2] -= 3 / 8
    cam = CameraModel(K, cam.width // 4, cam.height_px // 4, cam.T_base_cam, cam.mount_height)
    ground, opts = syn.default_ground(0), syn.RenderOptions(supersample=2, noise_std=0.0, vignette=0.0)
    poses = [(0.0, 0.0, 0.0), (1.0, 0.02, 0.01)]
    imgs = torch.stack([torch.from_numpy(syn.render_view(ground, cam, p, (0.0, 0.0), opts)) for p in poses])
    imgs = imgs.double()[:, None] / 255.0
    motion = torch.tensor([[1.0, 0.02, 0.01]], dtype=torch.float64)
    ta, ts = registration_from_vehicle_motion(motion, spec)

    def loss(pitch):
        bev, mask = project_to_bev(imgs, cam, pitch.expand(2), torch.zeros(2, dtype=torch.float64), spec)
        reg = register(bev[:1], bev[1:], mask[:1], mask[1:], DpcConfig())
        return registration_kl_loss(reg, ta, ts, math.radians(1.0), 1.0)

    p = torch.tensor([0.0], dtype=torch.float64, requires_grad=True)
    L = loss(p)
    (g,) = torch.autograd.grad(L, p)
    eps = 1e-7
    with torch.no_grad():
        fd = (loss(p + eps) - loss(p - eps)) / (2 * eps)
    print(f"\nloss {float(L.detach()):.4f}, dL/dpitch autograd {float(g):.5g}, finite differences {float(fd):.5g}")
    assert torch.isfinite(g).all() and float(g.abs()) > 0
    assert math.isclose(float(g), float(fd), rel_tol=2e-2)


def test_bad_targets_raise():
    reg = SimpleNamespace(rotation_log_prob=torch.zeros(2, 8), rotation_bins=torch.zeros(8),
                          translation_log_prob=torch.zeros(2, 4, 4), translation_bins=shift_bins(4))
    with pytest.raises(ValueError, match="target_angle"):
        registration_kl_loss(reg, torch.zeros(3), torch.zeros(2, 2))
