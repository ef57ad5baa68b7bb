"""core.phase_correlation: accuracy on warped textures, cv2 oracle, gradients, speed, errors."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bevo_ros.core.phase_correlation import (
    DpcConfig,
    angle_bins,
    prepare,
    register,
    register_prepared,
    rotate_about_centre,
    shift_bins,
)

S = 100


def texture(n: int, seed: int, smooth: float = 1.2) -> torch.Tensor:
    """Band-limited random texture ``(1, 1, n, n)`` float64 (periodic, no edges)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(1, 1, n, n, generator=g, dtype=torch.float64)
    k = torch.fft.fftfreq(n, dtype=torch.float64)
    X = torch.fft.fft2(x) * torch.exp(-2 * math.pi**2 * smooth**2 * (k[:, None] ** 2 + k[None, :] ** 2))
    x = torch.fft.ifft2(X).real
    return (x - x.mean()) / x.std() * 0.15 + 0.5


def warp(big: torch.Tensor, angle_deg: float, shift: tuple[float, float]) -> torch.Tensor:
    """A 100x100 view of ``big`` (centred): ``out(q) = big_view(c + R(-angle)(q - c) - shift)``,
    the registration model of phase_correlation (shift first, then rotation about the centre)."""
    n = big.shape[-1]
    i = torch.arange(S, dtype=torch.float64) - (S - 1) / 2
    r, k = torch.meshgrid(i, i, indexing="ij")
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    sr = c * r + s * k - shift[0]
    sc = -s * r + c * k - shift[1]
    half = (n - 1) / 2
    grid = torch.stack([(2 * (sc + half) + 1) / n - 1, (2 * (sr + half) + 1) / n - 1], -1)[None]
    return F.grid_sample(big, grid, mode="bicubic", align_corners=False)


@pytest.fixture(scope="module")
def big() -> torch.Tensor:
    return texture(3 * S, 0)


def _register_cases(big, cases, config=None, dtype=torch.float32):
    prev = warp(big, 0.0, (0.0, 0.0)).expand(len(cases), 1, S, S)
    curr = torch.cat([warp(big, a, s) for a, s in cases])
    mask = torch.ones_like(prev)
    reg = register(prev.to(dtype), curr.to(dtype), mask.to(dtype), mask.to(dtype), config or DpcConfig())
    ta = torch.tensor([a for a, _ in cases], dtype=torch.float64)
    ts = torch.tensor([s for _, s in cases], dtype=torch.float64)
    ea = (torch.rad2deg(reg.angle.double()) - ta).abs()
    es = (reg.shift.double() - ts).norm(dim=-1)
    return reg, ea, es


def test_recovers_rotation_and_shift(big):
    """Rotations within +-20 deg to <= 0.3 deg, shifts within +-30 px to <= 0.5 px."""
    rng = np.random.default_rng(0)
    cases = [(float(a), (float(rng.uniform(-12, 12)), float(rng.uniform(-12, 12)))) for a in np.linspace(-20, 20, 9)]
    cases += [(float(rng.uniform(-3, 3)), (float(r), float(c))) for r, c in
              [(30, 0), (-30, 0), (0, 30), (0, -30), (20, -20), (-21.5, 17.3), (11.7, 0.4), (0.3, -0.6)]]
    cases += [(float(rng.uniform(-2, 2)), (float(rng.uniform(5, 15)), float(rng.uniform(-2, 2)))) for _ in range(8)]
    reg, ea, es = _register_cases(big, cases)
    for (a, s), e1, e2, q in zip(cases, ea, es, reg.quality):
        print(f"\nangle {a:+7.2f} shift ({s[0]:+6.2f},{s[1]:+6.2f}): angle err {float(e1):.4f} deg, "
              f"shift err {float(e2):.4f} px, quality {float(q):.3f}", end="")
    print(f"\nangle err mean {float(ea.mean()):.4f} max {float(ea.max()):.4f} deg; "
          f"shift err mean {float(es.mean()):.4f} max {float(es.max()):.4f} px")
    assert float(ea.max()) <= 0.3
    assert float(es.max()) <= 0.5


def test_angle_range_and_ambiguity(big):
    """Angles live in [-90, 90): a 100 deg rotation is reported as -80 deg (period 180)."""
    reg, _, _ = _register_cases(big, [(100.0, (2.0, 1.0)), (-95.0, (0.0, 0.0)), (45.0, (3.0, -2.0))])
    got = torch.rad2deg(reg.angle.double())
    print(f"\n100 -> {float(got[0]):.3f}, -95 -> {float(got[1]):.3f}, 45 -> {float(got[2]):.3f} deg")
    assert abs(float(got[0]) + 80.0) < 0.3
    assert abs(float(got[1]) - 85.0) < 0.3
    assert abs(float(got[2]) - 45.0) < 0.3
    assert bool((reg.angle >= -math.pi / 2).all() and (reg.angle < math.pi / 2).all())


def test_translation_agrees_with_cv2(big):
    """Translation-only: same shift as cv2.phaseCorrelate (which returns (dx=col, dy=row) of b vs a)."""
    shifts = [(3.25, -7.5), (-11.6, 4.1), (0.4, 0.2), (17.0, -2.3), (-6.75, -9.25)]
    reg, _, es = _register_cases(big, [(0.0, s) for s in shifts])
    prev = warp(big, 0.0, (0.0, 0.0))[0, 0].numpy()
    win = cv2.createHanningWindow((S, S), cv2.CV_64F)
    for i, s in enumerate(shifts):
        curr = warp(big, 0.0, s)[0, 0].numpy()
        (dx, dy), _ = cv2.phaseCorrelate(prev, curr, win)
        ours = reg.shift[i].double()
        print(f"\ntrue ({s[0]:+.2f},{s[1]:+.2f}) ours ({float(ours[0]):+.3f},{float(ours[1]):+.3f}) "
              f"cv2 ({dy:+.3f},{dx:+.3f})", end="")
        assert abs(float(ours[0]) - dy) < 0.25 and abs(float(ours[1]) - dx) < 0.25
    print(f"\nours: shift err max {float(es.max()):.4f} px")
    assert float(es.max()) < 0.2


def test_masked_footprint_does_not_pull_to_zero(big):
    """A fixed invalid region (same in both frames) must not bias the shift towards zero."""
    cases = [(0.0, (12.0, 0.5)), (1.0, (10.5, -1.0))]
    prev = warp(big, 0.0, (0.0, 0.0)).expand(2, 1, S, S).clone()
    curr = torch.cat([warp(big, a, s) for a, s in cases])
    mask = torch.ones_like(prev)
    mask[..., 80:, 60:] = 0.0  # e.g. the image's bottom-right corner, identical in every frame
    mask[..., :, :5] = 0.0
    reg = register(prev * mask, curr * mask, mask, mask, DpcConfig())
    for (a, s), ang, sh in zip(cases, reg.angle, reg.shift):
        print(f"\ntrue {a:+.2f} deg ({s[0]:+.2f},{s[1]:+.2f}); got {math.degrees(float(ang)):+.3f} deg "
              f"({float(sh[0]):+.3f},{float(sh[1]):+.3f})", end="")
        assert abs(math.degrees(float(ang)) - a) < 0.3
        assert abs(float(sh[0]) - s[0]) < 0.5 and abs(float(sh[1]) - s[1]) < 0.5


def test_rotate_about_centre_convention():
    """+angle turns the row axis towards the column axis (counter-clockwise on screen)."""
    img = torch.zeros(1, 1, 9, 9, dtype=torch.float64)
    img[0, 0, 6, 4] = 1.0  # two rows below the centre (4, 4)
    out = rotate_about_centre(img, torch.tensor([math.pi / 2], dtype=torch.float64))
    r, c = divmod(int(out.argmax()), 9)
    print(f"\n(6, 4) rotated by +90 deg -> ({r}, {c})")
    assert (r, c) == (4, 6)


def test_distributions_and_spread(big):
    reg, _, _ = _register_cases(big, [(3.0, (4.0, -2.0)), (-1.0, (9.5, 0.5))])
    A, B = DpcConfig().angle_bins, 2
    assert reg.rotation_prob.shape == (B, A) and reg.rotation_bins.shape == (A,)
    assert reg.translation_prob.shape == (B, S, S) and reg.translation_bins.shape == (S, S, 2)
    assert torch.allclose(reg.rotation_prob.sum(-1), torch.ones(B), atol=1e-5)
    assert torch.allclose(reg.translation_prob.sum((-1, -2)), torch.ones(B), atol=1e-5)
    assert torch.allclose(reg.rotation_bins, angle_bins(DpcConfig()))
    assert torch.equal(reg.translation_bins, shift_bins(S))
    # The most likely cells are the true ones.
    j = reg.translation_prob.reshape(B, -1).argmax(-1)
    cells = reg.translation_bins.reshape(-1, 2)[j]
    print(f"\nmost likely cells {cells.tolist()}, quality {reg.quality.tolist()}, "
          f"angle std {torch.rad2deg(reg.angle_std).tolist()} deg, shift std "
          f"{reg.shift_cov.diagonal(dim1=-2, dim2=-1).sqrt().tolist()} px")
    assert cells.tolist() == [[4.0, -2.0], [10.0, 0.0]] or cells.tolist() == [[4.0, -2.0], [9.0, 0.0]]
    assert bool(((reg.quality > 0.2) & (reg.quality <= 1.0)).all())
    assert bool((torch.linalg.eigvalsh(reg.shift_cov) >= -1e-6).all())
    # An unrelated pair: low quality, wide spread.
    other = warp(texture(3 * S, 5), 0.0, (0.0, 0.0)).float()
    ones = torch.ones_like(other)
    bad = register(warp(big, 0.0, (0.0, 0.0)).float(), other, ones, ones)
    print(f"unrelated pair: quality {float(bad.quality):.3f}, shift std {bad.shift_cov[0].diagonal().sqrt().tolist()}")
    assert float(bad.quality) < float(reg.quality.min()) / 2


def test_gradients_are_finite_and_match_finite_differences(big):
    """Directional derivatives of angle, shift and the KL loss through register() (float64)."""
    from bevo_ros.core.loss import registration_kl_loss

    cfg = DpcConfig()
    prev = warp(big, 0.0, (0.0, 0.0))
    curr0 = warp(big, 2.0, (5.3, -3.6))
    mask = torch.ones_like(prev)
    g = torch.Generator().manual_seed(3)
    v = torch.randn(curr0.shape, generator=g, dtype=torch.float64) * 0.01  # direction

    def outputs(curr):
        reg = register(prev, curr, mask, mask, cfg)
        loss = registration_kl_loss(reg, torch.tensor([math.radians(2.0)], dtype=torch.float64),
                                    torch.tensor([[5.3, -3.6]], dtype=torch.float64))
        return torch.stack([reg.angle[0], reg.shift[0, 0], reg.shift[0, 1], loss])

    curr = curr0.clone().requires_grad_(True)
    out = outputs(curr)
    grads = [torch.autograd.grad(o, curr, retain_graph=True)[0] for o in out]
    ad = torch.stack([(gr * v).sum() for gr in grads])
    # Phase normalisation makes the map rough on coarse scales (the phase of weak frequencies
    # turns fast), so the difference quotient converges only for small steps.
    eps = 1e-6
    with torch.no_grad():
        fd = (outputs(curr0 + eps * v) - outputs(curr0 - eps * v)) / (2 * eps)
    print(f"\nautograd {ad.tolist()}\nfinite d {fd.tolist()}")
    assert all(bool(torch.isfinite(gr).all()) for gr in grads)
    assert torch.allclose(ad, fd, rtol=2e-3, atol=1e-7)


def test_prepared_reuse(big):
    """register_prepared == register (per-pair times: tools/bench_core.py)."""
    cfg = DpcConfig()
    prev = warp(big, 0.0, (0.0, 0.0)).float()
    curr = warp(big, 1.5, (11.0, 0.7)).float()
    mask = torch.ones_like(prev)
    a = register(prev, curr, mask, mask, cfg)
    pp, pc = prepare(prev, mask, cfg), prepare(curr, mask, cfg)
    b = register_prepared(pp, pc, cfg)
    assert torch.allclose(a.angle, b.angle) and torch.allclose(a.shift, b.shift)


def test_float64_and_batch_consistency(big):
    cases = [(4.0, (6.0, 2.0)), (-7.0, (-3.0, 9.0))]
    r32, _, _ = _register_cases(big, cases, dtype=torch.float32)
    r64, _, _ = _register_cases(big, cases, dtype=torch.float64)
    assert r64.angle.dtype == torch.float64 and r64.shift.dtype == torch.float64
    print(f"\nfloat32 vs float64: angle diff {float((r32.angle.double() - r64.angle).abs().max()):.2e} rad, "
          f"shift diff {float((r32.shift.double() - r64.shift).abs().max()):.2e} px")
    assert torch.allclose(r32.angle.double(), r64.angle, atol=1e-4)
    assert torch.allclose(r32.shift.double(), r64.shift, atol=1e-2)
    one, _, _ = _register_cases(big, cases[1:], dtype=torch.float64)
    assert torch.allclose(one.angle, r64.angle[1:], atol=1e-9) and torch.allclose(one.shift, r64.shift[1:], atol=1e-7)


def test_textureless_bev_is_no_information(big):
    """A uniform BEV (night, a lens cap) has an all-zero spectrum: the result must say "no
    information" (flat distributions, quality 0), not a confident zero motion, and gradients stay
    finite for training."""
    dpc = DpcConfig()
    mask = torch.ones(1, 1, S, S, dtype=torch.float64)
    for value in (0.0, 0.5):
        flat = torch.full((1, 1, S, S), value, dtype=torch.float64, requires_grad=True)
        reg = register_prepared(prepare(flat, mask, dpc), prepare(flat, mask, dpc), dpc)
        (grad,) = torch.autograd.grad(reg.rotation_quality.sum() + reg.angle_std.sum(), flat)
        rq, std, q = (float(v.detach()) for v in (reg.rotation_quality, reg.angle_std, reg.quality))
        print(f"\nuniform BEV {value}: rotation quality {rq:.3f}, angle std {math.degrees(std):.1f} deg, "
              f"translation quality {q:.3f}")
        assert rq < 0.05 and q < 0.05
        assert math.degrees(std) > 30.0  # ~uniform over the 180 degrees
        assert bool(torch.isfinite(grad).all())
    # A textured BEV registers with a sharp peak: the same checks fail there.
    tex = big.reshape(3 * S, 3 * S)[S : 2 * S, S : 2 * S].double().reshape(1, 1, S, S)
    reg = register_prepared(prepare(tex, mask, dpc), prepare(tex, mask, dpc), dpc)
    assert float(reg.rotation_quality) > 0.5 and math.degrees(float(reg.angle_std)) < 1.0


def test_bad_input_raises():
    x = torch.rand(2, 1, S, S)
    m = torch.ones_like(x)
    with pytest.raises(ValueError, match="bev must be"):
        register(x[:, 0], x[:, 0], m[:, 0], m[:, 0])
    with pytest.raises(ValueError, match="mask must have"):
        register(x, x, m[:, :, :50], m)
    with pytest.raises(ValueError, match="differ"):
        register(x, x[:1], m, m[:1])
    with pytest.raises(ValueError, match="no valid pixels"):
        register(x, x, torch.zeros_like(m), m)
    with pytest.raises(ValueError, match="angle_bins"):
        DpcConfig(angle_bins=7)
    with pytest.raises(ValueError, match="radial_range"):
        DpcConfig(radial_range=(0.3, 0.2))
    with pytest.raises(ValueError, match="temperature"):
        DpcConfig(rotation_temperature=0.0)


def test_a_second_motion_in_view_yields_to_the_prior(big):
    """A car ahead: a high-contrast block over the far centre (40 % of the BEV) that keeps its place
    while the road moves 4 px. Its peak is the highest; with a prior near the road's motion (a
    motion filter's prediction) the road's is taken, the car's region weighted out; a prior at
    the car's motion keeps the car's; without one nothing changes."""
    from bevo_ros.core.phase_correlation import motion_consistency_weight

    car_tex = (texture(3 * S, 1, smooth=0.8) - 0.5) * 3 + 0.5
    region = torch.zeros(1, 1, S, S, dtype=torch.float64)
    region[..., 0:45, 30:70] = 1

    def frame(road_shift, car_shift):
        return warp(big, 0.0, road_shift) * (1 - region) + warp(car_tex, 0.0, car_shift) * region

    prev, curr = frame((0.0, 0.0), (0.0, 0.0)), frame((4.0, 0.0), (0.0, 0.0))
    mask = torch.ones_like(prev).float()
    cfg = DpcConfig()
    p, c = prepare(prev.float(), mask, cfg), prepare(curr.float(), mask, cfg)
    plain = register_prepared(p, c, cfg)
    assert plain.shift[0].norm() < 0.3 and plain.shift_gated is None  # the car's: it moved 0
    std = torch.tensor([[1.0, 1.0]])
    road = register_prepared(p, c, cfg, shift_prior=torch.tensor([[3.5, 0.3]]), shift_prior_std=std)
    assert (road.shift[0] - torch.tensor([4.0, 0.0])).norm() < 0.25, road.shift
    assert road.shift_cov[0].diagonal().max() < 4.0  # the spread about the road's peak, not over both
    w = motion_consistency_weight(p.spectrum, c.image, torch.tensor([[3.5, 0.3]]))
    assert w.shape == (1, S, S)
    assert w[0, 5:40, 35:65].mean() < 0.4 and w[0, 55:95, 10:90].mean() > 0.9
    car = register_prepared(p, c, cfg, shift_prior=torch.tensor([[0.2, 0.0]]), shift_prior_std=std)
    assert car.shift[0].norm() < 0.3


def test_a_forward_range_takes_the_strongest_peak_inside_it(big):
    """The car ahead pulling away: its block moves -5 px (backwards in the BEV, as the road would if
    the car reversed) and outweighs the road's +2 px. Plain, the car's motion is read; with the
    rows limited to forward motion (``forward_range`` [-1, inf), the engine's direction of travel)
    the road's, and the distribution stays whole. A range whose edge sits on the flank of the
    excluded peak does not slide out to it: the peak taken is a peak inside the range, the road's."""
    car_tex = (texture(3 * S, 1, smooth=0.8) - 0.5) * 3 + 0.5
    region = torch.zeros(1, 1, S, S, dtype=torch.float64)
    region[..., 0:45, 30:70] = 1

    def frame(road_shift, car_shift):
        return warp(big, 0.0, road_shift) * (1 - region) + warp(car_tex, 0.0, car_shift) * region

    prev, curr = frame((0.0, 0.0), (0.0, 0.0)), frame((2.0, 0.0), (-5.0, 0.0))
    mask = torch.ones_like(prev).float()
    cfg = DpcConfig()
    p, c = prepare(prev.float(), mask, cfg), prepare(curr.float(), mask, cfg)
    plain = register_prepared(p, c, cfg)
    assert (plain.shift[0] - torch.tensor([-5.0, 0.0])).norm() < 0.3, plain.shift  # the car's
    forward = register_prepared(p, c, cfg, forward_range=torch.tensor([[-1.0, math.inf]]))
    assert (forward.shift[0] - torch.tensor([2.0, 0.0])).norm() < 0.5, forward.shift  # no weight: the car's edges pull
    assert bool(forward.shift_gated[0])
    assert torch.equal(forward.translation_log_prob, plain.translation_log_prob)
    edge = register_prepared(p, c, cfg, forward_range=torch.tensor([[-4.0, math.inf]]))  # row -4: the car's flank
    assert (edge.shift[0] - torch.tensor([2.0, 0.0])).norm() < 0.5, edge.shift
    backward = register_prepared(p, c, cfg, forward_range=torch.tensor([[-math.inf, 1.0]]))
    assert (backward.shift[0] - torch.tensor([-5.0, 0.0])).norm() < 0.3 and not bool(backward.shift_gated[0])
