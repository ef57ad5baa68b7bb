"""core.bev: inverse perspective mapping against the exact synthetic ground, gradients, errors."""
from __future__ import annotations

import math
import time

import pytest
import torch

from bevo_ros.datasets import synthetic as syn
from bevo_ros.core.bev import bev_sampling_grid, project_to_bev
from bevo_ros.core.geometry import BevSpec, CameraModel

SPEC = BevSpec()


def half_res_camera(dtype=torch.float64) -> CameraModel:
    """The KITTI-like camera at half resolution (renders 4x faster, same geometry)."""
    cam = syn.kitti_like_camera(dtype=torch.float64)
    K = cam.K.clone()
    K[:2, :2] /= 2
    K[:2, 2] = (K[:2, 2] + 0.5) / 2 - 0.5  # pixel centres at integers before and after
    return CameraModel(K.to(dtype), cam.width // 2, cam.height_px // 2, cam.T_base_cam.to(dtype), cam.mount_height)


def ncc(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    m = mask > 0.5
    a, b = a[m].double(), b[m].double()
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / (a.norm() * b.norm()))


@pytest.mark.parametrize("pitch_deg,roll_deg", [(0.0, 0.0), (2.0, -1.0), (-2.0, 1.0), (4.0, 2.0), (-4.0, -2.0)])
def test_bev_matches_true_ground(pitch_deg, roll_deg):
    """BEV of a rendered frame with the true attitude == the exact ground texture under it."""
    cam = syn.kitti_like_camera(dtype=torch.float64)
    ground = syn.default_ground(0)
    pose = (3.0, -1.0, 0.3)
    pr = (math.radians(pitch_deg), math.radians(roll_deg))
    opts = syn.RenderOptions(supersample=2, noise_std=0.0, vignette=0.0)
    img = syn.render_view(ground, cam, pose, pr, opts)
    image = torch.from_numpy(img).double()[None, None] / 255.0
    p, r = torch.tensor([pr[0]], dtype=torch.float64), torch.tensor([pr[1]], dtype=torch.float64)
    t0 = time.perf_counter()
    bev, mask = project_to_bev(image, cam, p, r, SPEC)
    dt = time.perf_counter() - t0
    truth = syn.ground_patch(pose[0], pose[1], pose[2], SPEC, ground, supersample=3, dtype=torch.float64)
    score = ncc(bev[0, 0], truth, mask[0, 0])
    # The wrong attitude must score clearly worse: the test can fail.
    bev_wrong, mask_wrong = project_to_bev(image, cam, p + math.radians(1.0), r, SPEC)
    wrong = ncc(bev_wrong[0, 0], truth, mask_wrong[0, 0] * mask[0, 0])
    print(f"\npitch {pitch_deg:+.0f} roll {roll_deg:+.0f} deg: NCC {score:.4f} (1 deg pitch off: {wrong:.4f}), "
          f"valid {float(mask.mean()):.3f}, project {dt * 1e3:.1f} ms")
    assert mask.mean() > 0.5
    assert score >= 0.95
    assert wrong < score - 0.05


def test_bev_gradient_matches_finite_differences():
    """d(BEV)/d(pitch, roll) by autograd == central differences (float64, smooth image)."""
    cam = half_res_camera()
    g = torch.Generator().manual_seed(0)
    H, W = cam.height_px, cam.width
    # Smooth image: a few low-frequency sinusoids (bilinear kinks stay negligible).
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    img = sum(torch.sin(u * float(torch.rand(1, generator=g)) * 0.2 + v * float(torch.rand(1, generator=g)) * 0.2
                        + float(torch.rand(1, generator=g)) * 6) for _ in range(4))
    img = (img / 8 + 0.5)[None, None]
    w = torch.rand(1, 1, SPEC.size, SPEC.size, generator=g, dtype=torch.float64)
    p0 = torch.tensor([math.radians(1.0)], dtype=torch.float64, requires_grad=True)
    r0 = torch.tensor([math.radians(-0.5)], dtype=torch.float64, requires_grad=True)
    # The mask is a hard (non-differentiable) function: keep its edge out of the comparison.
    _, mask0 = project_to_bev(img, cam, p0.detach(), r0.detach(), SPEC)
    w = w * (1.0 - torch.nn.functional.max_pool2d(1.0 - mask0, 5, stride=1, padding=2))

    def f(p: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        bev, mask = project_to_bev(img, cam, p, r, SPEC, supersample=2)
        return (bev * w).sum()

    gp, gr = torch.autograd.grad(f(p0, r0), (p0, r0))
    # Bilinear interpolation has kinks at pixel boundaries: a tiny step keeps the share of
    # samples that cross one (and bias the difference quotient) negligible.
    eps = 1e-8
    with torch.no_grad():
        fd_p = (f(p0 + eps, r0) - f(p0 - eps, r0)) / (2 * eps)
        fd_r = (f(p0, r0 + eps) - f(p0, r0 - eps)) / (2 * eps)
    rel_p = float((gp - fd_p).abs() / fd_p.abs())
    rel_r = float((gr - fd_r).abs() / fd_r.abs())
    print(f"\ndBEV/dpitch autograd {float(gp):.6g} fd {float(fd_p):.6g} rel {rel_p:.2e}; "
          f"dBEV/droll autograd {float(gr):.6g} fd {float(fd_r):.6g} rel {rel_r:.2e}")
    assert rel_p < 1e-3 and rel_r < 1e-3


def test_sampling_grid_pixel_centres():
    """A BEV point straight below the principal ray lands on the principal point (pixel centres)."""
    cam = half_res_camera()
    # Choose a spec whose centre column is on the camera's optical plane: the camera sits at y=0.
    spec = BevSpec(size=11, metres_per_pixel=0.5, forward_offset=6.0)
    grid, valid = bev_sampling_grid(cam, torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64), spec)
    assert grid.shape == (1, 11, 11, 2) and valid.shape == (1, 11, 11)
    # Column 5 is y = 0: u must be cx for every row (camera at y = 0, no roll, no yaw).
    assert valid[0, :, 5].sum() >= 5
    gx = grid[0, :, 5, 0][valid[0, :, 5]]
    u = ((gx + 1.0) * cam.width - 1.0) / 2.0
    print(f"\nu of the centre column: {u.min():.6f}..{u.max():.6f}, cx = {float(cam.K[0, 2]):.6f}")
    assert torch.allclose(u, cam.K[0, 2].expand_as(u), atol=1e-6)


def test_mask_behind_camera_and_outside_image():
    cam = half_res_camera()
    z = torch.zeros(1, dtype=torch.float64)
    far = BevSpec(size=20, metres_per_pixel=0.1, forward_offset=500.0)  # beyond the horizon row margin
    behind = BevSpec(size=20, metres_per_pixel=0.1, forward_offset=-30.0)  # behind the camera
    img = torch.rand(1, 1, cam.height_px, cam.width, dtype=torch.float64)
    for spec in (behind,):
        bev, mask = project_to_bev(img, cam, z, z, spec)
        assert float(mask.sum()) == 0.0 and float(bev.abs().sum()) == 0.0
    bev, mask = project_to_bev(img, cam, z, z, far)
    print(f"\nvalid fraction 500 m ahead: {float(mask.mean()):.3f}")
    # Pitching the nose up 10 degrees moves the near road out of the bottom of the image.
    _, m0 = project_to_bev(img, cam, z, z, SPEC)
    _, m1 = project_to_bev(img, cam, z - math.radians(10.0), z, SPEC)
    print(f"valid fraction level {float(m0.mean()):.3f}, nose up 10 deg {float(m1.mean()):.3f}")
    assert float(m1.mean()) < float(m0.mean())


def test_batch_and_dtype_and_speed():
    """Batched == one by one; float32 works; print the projection time at KITTI size."""
    cam = syn.kitti_like_camera(dtype=torch.float32)
    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, 1, cam.height_px, cam.width, generator=g)
    p = torch.tensor([0.0, 0.01, -0.02])
    r = torch.tensor([0.0, -0.01, 0.02])
    bev, mask = project_to_bev(img, cam, p, r, SPEC)
    for i in range(3):
        b1, m1 = project_to_bev(img[i : i + 1], cam, p[i : i + 1], r[i : i + 1], SPEC)
        assert torch.allclose(b1, bev[i : i + 1], atol=1e-6) and torch.equal(m1, mask[i : i + 1])
    assert bev.dtype == torch.float32 and mask.dtype == torch.float32
    for ss in (1, 2, 3):
        project_to_bev(img[:1], cam, p[:1], r[:1], SPEC, supersample=ss)
        t0 = time.perf_counter()
        for _ in range(5):
            project_to_bev(img[:1], cam, p[:1], r[:1], SPEC, supersample=ss)
        print(f"\nproject_to_bev 1241x376 -> 100x100, supersample {ss}: {(time.perf_counter() - t0) / 5 * 1e3:.2f} ms")


def test_uint8_image_equals_float_image():
    """uint8 is sampled as is and the BEV scaled by 1/255: the same as projecting image / 255."""
    cam = half_res_camera(torch.float32)
    g = torch.Generator().manual_seed(3)
    img8 = torch.randint(0, 256, (2, 1, cam.height_px, cam.width), generator=g, dtype=torch.uint8)
    p, r = torch.tensor([0.01, -0.02]), torch.tensor([0.0, 0.015])
    b8, m8 = project_to_bev(img8, cam, p, r, SPEC)
    bf, mf = project_to_bev(img8.float() / 255.0, cam, p, r, SPEC)
    diff = float((b8 - bf).abs().max())
    print(f"\nuint8 vs float/255 BEV: max diff {diff:.1e}, valid {float(m8.mean()):.3f}")
    assert b8.dtype == torch.float32 and torch.equal(m8, mf) and float(m8.mean()) > 0.5
    assert diff < 1e-6 and float(bf.max()) > 0.5


def test_bad_input_raises():
    cam = half_res_camera(torch.float32)
    z = torch.zeros(1)
    img = torch.rand(1, 1, cam.height_px, cam.width)
    with pytest.raises(ValueError, match="image must be"):
        project_to_bev(img[0], cam, z, z, SPEC)
    with pytest.raises(ValueError, match="float tensor in \\[0, 1\\] or uint8"):
        project_to_bev((img * 255).to(torch.int32), cam, z, z, SPEC)
    with pytest.raises(ValueError, match="camera model is"):
        project_to_bev(img[..., :-1], cam, z, z, SPEC)
    with pytest.raises(ValueError, match="pitch and roll"):
        project_to_bev(img, cam, z, torch.zeros(2), SPEC)
    with pytest.raises(ValueError, match="batch mismatch"):
        project_to_bev(img, cam, torch.zeros(2), torch.zeros(2), SPEC)
    with pytest.raises(ValueError, match="supersample"):
        project_to_bev(img, cam, z, z, SPEC, supersample=0)


def test_grids_cached_in_inference_mode_serve_autograd():
    """The engine runs in torch.inference_mode; the grids and windows it caches first
    (core.device.constant_cache) must still be usable by training's autograd afterwards."""
    from bevo_ros.core.phase_correlation import DpcConfig, prepare, register_prepared

    cam = half_res_camera(torch.float32)
    spec = BevSpec(size=36, metres_per_pixel=0.25, forward_offset=6.0)  # sizes no other test caches
    dpc = DpcConfig(angle_bins=90, radial_samples=11)
    image = torch.rand(1, 1, cam.height_px, cam.width, generator=torch.Generator().manual_seed(0))

    def step(pitch):
        bev, mask = project_to_bev(image.expand(2, -1, -1, -1), cam, pitch, pitch * 0.5, spec)
        p = prepare(bev, mask, dpc)
        reg = register_prepared(p[:1], p[1:], dpc)
        return reg.shift.sum() + reg.angle.sum() + reg.translation_log_prob.logsumexp(dim=(-1, -2)).sum()

    with torch.inference_mode():
        step(torch.tensor([0.01, 0.012]))
    pitch = torch.tensor([0.01, 0.012], requires_grad=True)
    step(pitch).backward()
    assert pitch.grad is not None and torch.isfinite(pitch.grad).all()


def test_projection_mask_is_every_sub_sample_valid():
    """project_to_bev reduces the inside test as max(|g - mid| - half) <= 0 (cheaper than boolean
    tensors): the same mask as bev_sampling_grid's per-sample test, over attitudes that cut the
    ground patch at the image border, and the sign rule holds on exact ties."""
    cam = half_res_camera(torch.float32)
    spec = BevSpec(size=40, metres_per_pixel=0.25, forward_offset=2.0)  # near rows leave the image
    image = torch.rand(1, 1, cam.height_px, cam.width, generator=torch.Generator().manual_seed(1))
    partial = 0
    for pitch, roll in [(0.0, 0.0), (0.05, 0.02), (-0.08, -0.05), (0.2, 0.1), (-0.3, 0.2)]:
        p, r = torch.tensor([pitch]), torch.tensor([roll])
        _, mask = project_to_bev(image, cam, p, r, spec)
        _, valid = bev_sampling_grid(cam, p, r, spec, supersample=2)
        expected = valid.reshape(1, 1, 4, spec.size, spec.size).all(dim=2).to(mask.dtype)
        assert torch.equal(mask, expected)
        partial += 0 < int(expected.sum()) < spec.size**2
    assert partial >= 3  # the masks were cut, not all-in or all-out
    a = torch.tensor([1.0, 0.5, 1e-38, 3e-39, 1.0000001])
    b = torch.tensor([1.0, 0.50000006, 1e-38, 2e-39, 1.0])
    assert torch.equal((a - b) <= 0, a <= b)  # ties, neighbours, subnormals


def _rotated(T: torch.Tensor, pitch: float = 0.0, roll: float = 0.0, yaw: float = 0.0) -> torch.Tensor:
    """``T_base_cam`` with the camera turned in the base frame by ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    from bevo_ros.core.geometry import rotation_x, rotation_y

    t = torch.tensor
    R = (torch.tensor([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]],
                      dtype=torch.float64)
         @ rotation_y(t(pitch, dtype=torch.float64)) @ rotation_x(t(roll, dtype=torch.float64)))
    out = T.clone().double()
    out[:3, :3] = R @ out[:3, :3]
    return out


def test_mounting_for_extrinsics_keeps_the_road_plane_in_the_camera():
    """Another calibration of the same camera (KITTI: ~1 deg of pitch between days' files): the
    re-derived base mounting puts the road's normal where the calibrated one had it in the camera
    frame (the plane the BEV projects onto), a pure pitch of the camera moves the mounting's pitch
    back by as much, and equal extrinsics give the mounting itself."""
    from bevo_ros.core.geometry import camera_pose_on_road, mounting_for_extrinsics

    base = syn.kitti_like_camera(scale=0.5)
    T_cal = base.T_base_cam.double()
    mounting = (0.0270, -0.0177)
    T_new = _rotated(T_cal, pitch=math.radians(1.0), roll=math.radians(0.4), yaw=math.radians(0.7))
    m = mounting_for_extrinsics(mounting, T_cal, T_new)

    def road_normal_in_camera(T, att):
        cam = CameraModel(base.K.double(), base.width, base.height_px, T, base.mount_height)
        R, _ = camera_pose_on_road(cam, torch.tensor([att[0]], dtype=torch.float64),
                                   torch.tensor([att[1]], dtype=torch.float64))
        return R[0, 2]  # the road's z axis in camera coordinates

    assert torch.allclose(road_normal_in_camera(T_new, m), road_normal_in_camera(T_cal, mounting), atol=1e-12)
    # without the re-derivation the plane is 1.1 deg off
    off = torch.acos((road_normal_in_camera(T_new, mounting) * road_normal_in_camera(T_cal, mounting)).sum().clamp(max=1))
    assert math.degrees(float(off)) > 1.0
    # a pure pitch of the camera by d about the base's y axis: the base's pitch on the road drops by d
    d = math.radians(0.97)
    p, r = mounting_for_extrinsics((0.03, 0.0), T_cal, _rotated(T_cal, pitch=d))
    assert p == pytest.approx(0.03 - d, abs=1e-12) and r == pytest.approx(0.0, abs=1e-12)
    assert mounting_for_extrinsics(mounting, T_cal, T_cal.float()) == mounting  # float32 copy: the same
    assert mounting_for_extrinsics(mounting, T_cal.numpy(), T_new.numpy()) == m  # arrays or tensors


def test_mounting_reference_camera_rederives_the_mounting_for_other_extrinsics():
    """``filter.mounting_reference``: ``camera`` keeps the camera's tilt when the engine's camera has
    other extrinsics than ``camera.base_T_camera`` (at construction and on ``set_camera``), ``base``
    keeps the mounting; an unknown value is a ConfigError."""
    import dataclasses

    import numpy as np

    from bevo_ros.config import BevoConfig, ConfigError, build_odometry, camera_model
    from bevo_ros.io.learned_params import LearnedParams

    config = BevoConfig()
    config.filter.mounting_pitch, config.filter.mounting_roll = 0.027, -0.0177
    T_cal = np.asarray(config.camera.base_T_camera, dtype=np.float64).reshape(4, 4)
    T_new = _rotated(torch.from_numpy(T_cal), pitch=math.radians(1.0)).numpy()
    config.camera = dataclasses.replace(config.camera, fx=300.0, fy=300.0, cx=160.0, cy=50.0, width=320, height_px=100)
    other = camera_model(dataclasses.replace(config.camera, base_T_camera=T_new.reshape(-1).tolist()))
    config.filter.mounting_reference = "base"
    assert build_odometry(config, LearnedParams(), other).mounting_attitude == (0.027, -0.0177)
    config.filter.mounting_reference = "camera"
    odo = build_odometry(config, LearnedParams(), other)
    assert math.degrees(odo.mounting_attitude[0] - 0.027) == pytest.approx(-1.0, abs=0.01)
    odo.set_camera(camera_model(config.camera))  # back to the calibrated extrinsics: the mounting as given
    assert odo.mounting_attitude == pytest.approx((0.027, -0.0177), abs=1e-7)
    config.filter.mounting_reference = "road"
    with pytest.raises(ConfigError, match="mounting_reference"):
        build_odometry(config, LearnedParams(), other)


def _extrinsics_switch(setup_only: bool = False):
    """A drive, the params' camera 1 deg of pitch off its own (the mounting calibrated through the
    params', ``mounting_reference: camera``) and ``run(switch_at)``: the engine's steps, handed the
    drive's own camera at frame ``switch_at`` (None: from the start). ``setup_only``: ``(drive,
    config, its own camera)``."""
    import dataclasses

    from bevo_ros.config import BevoConfig, build_odometry, camera_model
    from bevo_ros.core.geometry import mounting_for_extrinsics
    from bevo_ros.io.learned_params import LearnedParams

    d = syn.make_drive(seed=5, duration=1.5, camera=syn.kitti_like_camera(scale=0.25), render="lazy" if setup_only else True)
    T_true = d.camera.T_base_cam.double()
    T_params = _rotated(T_true, pitch=math.radians(1.0))
    config = BevoConfig()
    config.camera = dataclasses.replace(
        config.camera, fx=float(d.camera.K[0, 0]), fy=float(d.camera.K[1, 1]), cx=float(d.camera.K[0, 2]),
        cy=float(d.camera.K[1, 2]), width=d.camera.width, height_px=d.camera.height_px,
        mount_height=d.camera.mount_height, base_T_camera=T_params.reshape(-1).tolist())
    config.filter.mounting_pitch, config.filter.mounting_roll = mounting_for_extrinsics((0.0, 0.0), T_true, T_params)
    config.filter.mounting_reference = "camera"
    true_camera = camera_model(dataclasses.replace(config.camera, base_T_camera=T_true.reshape(-1).tolist()))
    if setup_only:
        return d, config, true_camera

    def run(switch_at: int | None) -> list:
        odo = build_odometry(config, LearnedParams(), true_camera if switch_at is None else camera_model(config.camera))
        steps, frames = [], {int(i): k for k, i in enumerate(d.frame_imu_index)}
        for i, t in enumerate(d.imu_stamps):
            odo.add_imu(float(t), d.gyro[i], d.accel[i])
            if i in frames:
                if frames[i] == switch_at:
                    odo.set_camera(true_camera)
                steps += odo.add_image(float(t), d.images[frames[i]])
        return steps

    return run


def test_other_extrinsics_mid_drive_keep_the_trajectory():
    """The node's case: frames already processed with the params' extrinsics, then /tf_static's
    (1 deg of pitch apart, the mounting calibrated through the params'): with
    ``mounting_reference: camera`` the switch leaves the camera's tilt, and the frame after it reads
    what it reads with /tf_static's extrinsics from the start (the last frame's BEV pitch moves
    with the mounting: kept, the pitch-change correction took the switch for a 1.46 m shift and the
    motion filter rejected the frame)."""
    import numpy as np

    run = _extrinsics_switch()
    switch = 8
    want, got = run(None), run(switch)
    a, b = want[switch], got[switch]
    print(f"frame {switch}, the first with /tf_static's extrinsics: pitch-change shift {a.pitch_shift:+.4f} / "
          f"{b.pitch_shift:+.4f} m, accepted {a.accepted} / {b.accepted}")
    assert abs(b.pitch_shift - a.pitch_shift) < 0.005 and b.accepted == a.accepted == (True, True)
    # the camera sits 1.3 cm further forward on the road and the DUKF started from the params' mounting:
    # millimetres per frame, before the switch as after it
    dx = np.array([s.motion[0] for s in got]) - np.array([s.motion[0] for s in want])
    assert np.abs(dx).max() < 0.02 and sum(s.motion[0] for s in want) > 8.0


def test_extrinsics_at_the_first_image_move_the_dukf_start():
    """The node's usual case: the IMU fused for a while (the DUKF started from the params' mounting),
    then the first image names the camera and /tf_static's extrinsics (1 deg of pitch apart) re-derive
    the mounting. The DUKF's start moves with it (``_move_dukf_start``): its attitude as if started
    from the re-derived mounting, the BEV's attitude unmoved. Without the move the DUKF stayed
    0.84 deg off after 1 sample; after 10 the move takes 0.18 deg of it (the start's share, tracked
    as a linear filter's, underestimates the UKF's)."""
    import math

    import numpy as np

    from bevo_ros.config import build_odometry, camera_model
    from bevo_ros.io.learned_params import LearnedParams

    d, config, true_camera = _extrinsics_switch(setup_only=True)
    for k, dukf_tol in ((1, 0.01), (10, 0.3)):
        moved = build_odometry(config, LearnedParams(), camera_model(config.camera))
        started = build_odometry(config, LearnedParams(), true_camera)
        for i in range(k + 20):
            if i == k:
                moved.set_camera(true_camera)
            for odo in (moved, started):
                odo.add_imu(float(d.imu_stamps[i]), d.gyro[i], d.accel[i])
        dukf = np.degrees(moved.pitch_roll - started.pitch_roll)
        road = np.degrees(moved.road_pitch_roll - started.road_pitch_roll)
        print(f"extrinsics after {k} IMU samples: DUKF {dukf.round(4).tolist()} deg, BEV attitude {road.round(4).tolist()} "
              "deg off the engine started with them")
        assert abs(dukf[0]) < dukf_tol and np.abs(road).max() < 0.005
        assert abs(math.degrees(moved.mounting_attitude[0])) < 1e-6


def test_uint8_projection_converts_only_the_rows_it_samples_bit_for_bit():
    """Outside autograd a uint8 image is converted to floats only over the rows the samples'
    bilinear footprints reach, into a per-thread buffer (core.bev._as_float): the BEV and mask are
    bit for bit those of converting the whole image (the path autograd takes), frame after frame
    with the buffer's other rows holding earlier frames, at attitudes that move the rows sampled."""
    from bevo_ros.core import bev as bev_module

    cam = syn.kitti_like_camera(dtype=torch.float32)
    g = torch.Generator().manual_seed(5)
    rows = []
    real = bev_module._as_float

    def spy(image, grid, dtype):
        out = real(image, grid, dtype)
        if out.data_ptr() != image.data_ptr() and not torch.equal(out, image.to(dtype)):
            rows.append(int((out != image.to(dtype)).any(dim=-1).sum()))  # rows left stale
        return out

    bev_module._buffers.images = {}  # the buffer is made in inference mode below (as by the engine)
    bev_module._as_float = spy
    try:
        for pitch_deg, roll_deg in [(0.0, 0.0), (1.5, -2.0), (-3.0, 4.0), (25.0, 0.0), (0.5, 0.5)]:
            img8 = torch.randint(0, 256, (1, 1, cam.height_px, cam.width), generator=g, dtype=torch.uint8)
            p, r = torch.tensor([math.radians(pitch_deg)]), torch.tensor([math.radians(roll_deg)])
            with torch.inference_mode():
                b8, m8 = project_to_bev(img8, cam, p, r, SPEC)
            whole, mw = project_to_bev(img8, cam, p.clone().requires_grad_(), r, SPEC)  # autograd: the whole image
            assert torch.equal(m8, mw) and torch.equal(b8, whole.detach()), (pitch_deg, roll_deg)
            # and outside inference mode, no gradient (a tool, a test): the same buffer, written there too
            b_out, _ = project_to_bev(img8, cam, p, r, SPEC)
            assert torch.equal(b_out, b8)
    finally:
        bev_module._as_float = real
    print(f"\nrows of the buffer not converted in each frame: {rows}")
    assert len(rows) == 10 and min(rows) > 0.4 * cam.height_px  # the buffer was used, most rows not converted
    # a batch (offline) is converted whole: no buffer of its size stays held
    batch = torch.randint(0, 256, (2, 1, cam.height_px, cam.width), generator=g, dtype=torch.uint8)
    with torch.inference_mode():
        project_to_bev(batch, cam, torch.zeros(2), torch.zeros(2), SPEC)
    assert all(key[0][0] == 1 for key in bev_module._buffers.images)
