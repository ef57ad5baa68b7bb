"""Synthetic drive: determinism, exact IMU, pose bookkeeping, renderer <-> ground <-> BEV geometry."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from bevo_ros.datasets import synthetic as syn
from bevo_ros.datasets.synthetic import ground as syn_ground
from bevo_ros.rotations import rpy_from_matrices
from bevo_ros.core.geometry import BevSpec, camera_pose_on_road

SPEC = BevSpec(size=100, metres_per_pixel=0.1, forward_offset=7.5)
IDEAL = syn.RenderOptions(supersample=1, noise_std=0.0, vignette=0.0, haze_start=1e4, haze_end=2e4)


@pytest.fixture(scope="module")
def drive() -> syn.SyntheticDrive:
    """20 s noise-free drive with curves, speed changes, bumps and road tilt; frames not rendered."""
    return syn.make_drive(seed=0, duration=20.0, noise=False, render=False)


@pytest.fixture(scope="module", params=[None, *syn.PRESETS, "vertical_curves"])
def any_drive(request, drive) -> syn.SyntheticDrive:
    """The random drive, every preset and a drive over crests and sags (noise-free, no images): the
    exactness checks run on each."""
    if request.param is None:
        return drive
    if request.param == "vertical_curves":
        return syn.make_drive(seed=0, duration=20.0, noise=False, render=False, vertical_curves=True)
    return syn.make_drive(seed=0, preset=request.param, noise=False, render=False)


def _so3_exp(v: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(v))
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + math.sin(th) / th * k + (1 - math.cos(th)) / th**2 * (k @ k)


def _rot_angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))


def _accel_to_pitch_roll(acc: np.ndarray) -> np.ndarray:
    """The DUKF measurement model of docs/ARCHITECTURE.md."""
    pitch = -np.arctan2(acc[:, 0], np.sqrt(acc[:, 1] ** 2 + acc[:, 2] ** 2))
    roll = np.arctan2(acc[:, 1], acc[:, 2])
    return np.stack([pitch, roll], 1)


def test_shapes_stamps_and_ranges(drive):
    F, N = drive.num_frames, len(drive.imu_stamps)
    print(f"\nframes {F}, imu samples {N}, t0 {drive.imu_stamps[0]}")
    assert (F, N) == (201, 2001)
    assert drive.imu_stamps[0] == 1000.0 and np.allclose(np.diff(drive.imu_stamps), 0.01)
    assert np.array_equal(drive.frame_stamps, drive.imu_stamps[drive.frame_imu_index])
    for name, shape in [("gyro", (N, 3)), ("accel", (N, 3)), ("poses_xy_yaw", (F, 3)), ("pitch_roll_road", (F, 2)),
                        ("pitch_roll_gravity", (F, 2)), ("relative_motion", (F - 1, 3)),
                        ("imu_pitch_roll_gravity", (N, 2)), ("imu_rotation_gravity", (N, 3, 3))]:
        assert getattr(drive, name).shape == shape, name
    speed = np.linalg.norm(drive.imu_velocity_gravity, axis=1)
    yaw_rate = np.abs(drive.gyro_true[:, 2]).max()
    pr = np.degrees(drive.pitch_roll_road)
    tilt = np.degrees(drive.road_slope_camber)
    print(f"speed {speed.min():.2f}..{speed.max():.2f} m/s, max |yaw rate| {yaw_rate:.3f} rad/s")
    print(f"road-relative pitch {pr[:, 0].min():.2f}..{pr[:, 0].max():.2f} deg, roll {pr[:, 1].min():.2f}..{pr[:, 1].max():.2f} deg")
    print(f"slope {tilt[:, 0].min():.2f}..{tilt[:, 0].max():.2f} deg, camber {tilt[:, 1].min():.2f}..{tilt[:, 1].max():.2f} deg")
    assert 4.9 < speed.min() and speed.max() < 15.2
    assert 0.05 < yaw_rate < 0.33
    assert 0.5 < np.abs(pr).max() < 5.0
    assert 1.0 < tilt[:, 1].mean() < 3.5


def test_deterministic_by_seed():
    # ground_seed=0 reuses the cached texture; texture determinism is checked on small tiles below.
    a = syn.make_drive(seed=5, duration=2.0, render="lazy", ground_seed=0)
    b = syn.make_drive(seed=5, duration=2.0, render="lazy", ground_seed=0)
    c = syn.make_drive(seed=6, duration=2.0, render=False, ground_seed=0)
    for name in ("gyro", "accel", "poses_xy_yaw", "pitch_roll_road", "relative_motion", "imu_velocity_gravity"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert not np.allclose(getattr(a, name), getattr(c, name)), name
    ia, ib = a.images[3], b.images[3]
    ic = syn.render_frame(c, 3)
    print(f"\nsame seed image diff {np.abs(ia.astype(int) - ib).max()}, other seed mean diff "
          f"{np.abs(ia.astype(int) - ic).mean():.1f} grey levels")
    assert ia.shape == (376, 1241) and ia.dtype == np.uint8
    assert np.array_equal(ia, ib) and np.array_equal(ia, syn.render_frame(a, 3))
    assert np.abs(ia.astype(int) - ic).mean() > 5
    t1, t2, t3 = (syn_ground._make_textures(sd, 512, 128)[0] for sd in (3, 3, 4))
    print(f"texture tiles: same seed equal {torch.equal(t1, t2)}, other seed mean diff {(t1 - t3).abs().mean():.3f}")
    assert torch.equal(t1, t2) and (t1 - t3).abs().mean() > 0.02


def _integration_error(w: np.ndarray, rot: np.ndarray, dt: np.ndarray, rule: str) -> float:
    """Largest attitude error (rad) integrating body rates ``w`` from ``rot[0]``: "end" takes each
    sample as its interval's rate, "trapezoid" is second order (with the commutator)."""
    r, err = rot[0].copy(), 0.0
    for k in range(len(w) - 1):
        if rule == "end":
            v = w[k + 1] * dt[k]
        else:
            v = 0.5 * (w[k] + w[k + 1]) * dt[k] + dt[k] ** 2 / 12 * np.cross(w[k], w[k + 1])
        r = r @ _so3_exp(v)
        err = max(err, _rot_angle(r, rot[k + 1]))
    return err


def test_gyro_integrates_to_attitude(any_drive):
    """Noise-free gyro = the mean body rate of R_grav_base over each sample interval (what a
    delta-angle IMU reports, the default ``gyro_sampling``): composing the samples reproduces the
    attitude to rounding."""
    drive = any_drive
    w, rot, dt = drive.gyro_true, drive.imu_rotation_gravity, np.diff(drive.imu_stamps)
    err = _integration_error(w, rot, dt, "end")
    # A rate expressed in the wrong frame (world instead of body) must not pass.
    err_w = _integration_error(np.einsum("nij,nj->ni", rot, w), rot, dt, "end")
    print(f"\ngyro integration over {drive.imu_stamps[-1] - drive.imu_stamps[0]:.0f} s: max attitude error {err:.2e} rad (world-frame rate: {err_w:.2e} rad)")
    assert err < 1e-6  # rounding (arccos near 1); the trapezoid on these rates: 2e-3 to 7e-3 rad
    assert err_w > 1e-2
    # The stored angles are the Euler angles of the stored rotation.
    r_, p_, _ = rpy_from_matrices(rot)
    assert np.allclose(np.stack([p_, r_], 1), drive.imu_pitch_roll_gravity, atol=1e-12)


@pytest.mark.parametrize("preset", ["bumpy", None])
def test_instantaneous_gyro_is_the_rate_at_the_stamp(preset):
    """``gyro_sampling="instantaneous"``: the body rate at each stamp, which a second-order rule
    integrates to the attitude (and which the interval-mean rule gets wrong on suspension motion)."""
    drive = syn.make_drive(seed=0, preset=preset, duration=10.0, noise=False, render=False, gyro_sampling="instantaneous")
    w, rot, dt = drive.gyro_true, drive.imu_rotation_gravity, np.diff(drive.imu_stamps)
    mean = syn.make_drive(seed=0, preset=preset, duration=10.0, noise=False, render=False).gyro_true
    err = _integration_error(w, rot, dt, "trapezoid")
    print(f"\ninstantaneous rates, trapezoid: max attitude error {err:.2e} rad; rates differ from the interval means by "
          f"up to {np.abs(w - mean).max():.2e} rad/s")
    assert err < 3e-4
    assert np.abs(w - mean).max() > 1e-4  # the two samplings are different signals
    with pytest.raises(ValueError, match="gyro_sampling"):
        syn.make_drive(seed=0, duration=1.0, render=False, gyro_sampling="averaged")


def test_accel_is_specific_force(any_drive):
    """R accel - g integrates to the true gravity-frame velocity."""
    drive = any_drive
    g = np.array([0.0, 0.0, syn.GRAVITY])
    a = np.einsum("nij,nj->ni", drive.imu_rotation_gravity, drive.accel_true) - g
    dt = np.diff(drive.imu_stamps)[:, None]
    v = drive.imu_velocity_gravity
    v_int = v[0] + np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (a[1:] + a[:-1]) * dt, 0)])
    err = np.abs(v_int - v).max()
    print(f"\naccel integration over {drive.imu_stamps[-1] - drive.imu_stamps[0]:.0f} s: max velocity error {err:.2e} m/s; |a_kin| max {np.abs(a).max(0).round(2)} m/s^2")
    assert err < 5e-3
    # Speed along the road matches the planar motion between frames (no lateral slip): the chord
    # between frames vs the speed's exact integral (arc), and vs the trapezoid of the frame speeds.
    step = np.linalg.norm(drive.relative_motion[:, :2], axis=1)
    # as lengths: parking reverses (standing where the direction changes)
    arc = np.abs(np.diff(drive._motion.speed_profile.integral(drive.frame_stamps - drive.imu_stamps[0])))
    trap = np.abs(0.1 * 0.5 * (drive.speed[1:] + drive.speed[:-1]))
    print(f"frame steps vs arc length: max rel err {np.abs(step - arc).max() / arc.max():.1e}, vs trapezoid "
          f"{np.abs(step - trap).max() / arc.max():.1e}")
    assert np.allclose(step, arc, rtol=1e-4, atol=1e-9)
    assert np.allclose(step, trap, rtol=2e-3, atol=2e-3 * arc.max())


def test_accel_gives_gravity_angles_when_unaccelerated():
    """Straight, constant speed, rigid, constant tilt: accel alone gives the OXTS pitch/roll."""
    slope, camber = 0.03, -0.045
    d = syn.make_drive(seed=2, duration=3.0, curvature=0.0, speed_variation=0.0, bumps=0.0,
                       road_tilt=(slope, camber), noise=False, render=False)
    pr = _accel_to_pitch_roll(d.accel_true)
    err = np.abs(pr - d.imu_pitch_roll_gravity).max()
    g_err = np.abs(np.linalg.norm(d.accel_true, axis=1) - syn.GRAVITY).max()
    print(f"\nunaccelerated: accel->pitch/roll error {err:.2e} rad, |accel|-g {g_err:.2e}, gyro max {np.abs(d.gyro_true).max():.1e}")
    assert err < 1e-8 and g_err < 1e-8
    assert np.allclose(d.imu_pitch_roll_gravity, [slope, camber], atol=1e-12)
    assert np.abs(d.gyro_true).max() < 1e-9
    # Without road tilt the gravity-referenced attitude is the road-relative one.
    flat = syn.make_drive(seed=2, duration=3.0, road_tilt=False, noise=False, render=False)
    assert np.allclose(flat.pitch_roll_gravity, flat.pitch_roll_road, atol=1e-12)


def test_grade_tilts_the_imu_only():
    """``grade`` adds a constant slope: the IMU's gravity pitch moves by it (positive nose down, the
    accelerometer's forward reading by -g sin), the images and the motion on the road do not, so one
    drive's cached frames serve any grade (tools/eval_real_imu.py --grade)."""
    grade = math.radians(4.0)
    flat = syn.make_drive(seed=3, preset="curve", duration=2.0, imu_rate=10, render="lazy", camera=syn.kitti_like_camera(scale=0.25))
    hill = syn.make_drive(seed=3, preset="curve", duration=2.0, imu_rate=10, render="lazy", camera=syn.kitti_like_camera(scale=0.25),
                          grade=grade)
    assert np.allclose(hill.imu_pitch_roll_gravity[:, 0] - flat.imu_pitch_roll_gravity[:, 0], grade, atol=1e-6)
    assert np.allclose(hill.imu_road_slope_camber[:, 0] - flat.imu_road_slope_camber[:, 0], grade, atol=1e-12)
    assert np.allclose(hill.accel_true[:, 0] - flat.accel_true[:, 0], -syn.GRAVITY * math.sin(grade), atol=0.02)
    assert np.array_equal(hill.relative_motion, flat.relative_motion)
    assert np.array_equal(hill.pitch_roll_road, flat.pitch_roll_road)
    assert np.array_equal(np.asarray(hill.images[5]), np.asarray(flat.images[5]))
    with pytest.raises(ValueError, match="grade"):
        syn.make_drive(duration=1.0, render=False, grade=0.5)
    with pytest.raises(ValueError, match="grade"):
        syn.make_drive(duration=1.0, render=False, grade=float("nan"))


def test_imu_noise_statistics():
    d = syn.make_drive(seed=3, duration=20.0, render=False)
    gyro_res = d.gyro - d.gyro_true - d.gyro_bias
    accel_res = d.accel - d.accel_true - d.accel_bias
    print(f"\ngyro white {gyro_res.std(0).round(4)} rad/s, bias {d.gyro_bias[0].round(4)}; "
          f"accel noise+vibration {accel_res.std(0).round(3)} m/s^2, bias {d.accel_bias[0].round(3)}")
    assert np.allclose(gyro_res.std(0), 0.005, rtol=0.1)
    assert np.all((accel_res.std(0) > 0.2) & (accel_res.std(0) < 1.5))
    assert np.abs(d.gyro_bias).max() < 0.02 and np.abs(d.gyro_bias).max() > 0
    quiet = syn.make_drive(seed=3, duration=2.0, noise=0.0, render=False)
    assert np.array_equal(quiet.gyro, quiet.gyro_true) and np.array_equal(quiet.accel, quiet.accel_true)


def test_relative_motion_composes_to_poses(any_drive):
    drive = any_drive
    poses = drive.poses_xy_yaw
    x, y, yaw = poses[0]
    out = [poses[0]]
    for dx, dy, dyaw in drive.relative_motion:
        x, y = x + math.cos(yaw) * dx - math.sin(yaw) * dy, y + math.sin(yaw) * dx + math.cos(yaw) * dy
        yaw = yaw + dyaw
        out.append((x, y, yaw))
    out = np.array(out)
    e_xy = np.abs(out[:, :2] - poses[:, :2]).max()
    e_yaw = np.abs(np.remainder(out[:, 2] - poses[:, 2] + np.pi, 2 * np.pi) - np.pi).max()
    print(f"\ncomposed relative motion: max xy error {e_xy:.1e} m, yaw error {e_yaw:.1e} rad, "
          f"path length {np.linalg.norm(drive.relative_motion[:, :2], axis=1).sum():.1f} m")
    assert e_xy < 1e-9 and e_yaw < 1e-12
    # 4x4 poses agree with the planar poses and the camera height contract.
    T = syn.base_poses_4x4(drive)
    assert np.allclose(T[:, :2, 3], poses[:, :2]) and np.allclose(np.arctan2(T[:, 1, 0], T[:, 0, 0]), poses[:, 2])
    assert np.allclose(syn.camera_poses_4x4(drive)[:, 2, 3], drive.camera.mount_height, atol=1e-12)


def _pixel_ground_points(drive, i: int, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent ray cast: camera pose from the 4x4 base pose, pinhole K, road plane z = 0."""
    T = syn.camera_poses_4x4(drive)[i]
    K = drive.camera.K.double().numpy()
    rays = T[:3, :3] @ np.linalg.solve(K, np.stack([u, v, np.ones_like(u)]))
    lam = -T[2, 3] / rays[2]
    return T[0, 3] + lam * rays[0], T[1, 3] + lam * rays[1]


def test_rendered_pixels_show_their_ground_point(drive):
    i = 37
    img = syn.render_frame(drive, i, IDEAL).astype(np.float64) / 255.0
    rng = np.random.default_rng(0)
    v = rng.integers(200, drive.camera.height_px, 300).astype(np.float64)
    u = rng.integers(0, drive.camera.width, 300).astype(np.float64)
    gx, gy = _pixel_ground_points(drive, i, u, v)
    truth = drive.ground_intensity(gx, gy)
    err = np.abs(img[v.astype(int), u.astype(int)] - truth).max() * 255
    # The same check with pixel corners instead of centres must fail: the test sees half a pixel.
    sx, sy = _pixel_ground_points(drive, i, u + 0.5, v + 0.5)
    err_shift = np.abs(img[v.astype(int), u.astype(int)] - drive.ground_intensity(sx, sy)).max() * 255
    print(f"\n300 ground pixels: max |pixel - ground intensity| {err:.2f} grey levels "
          f"(half-pixel-shifted convention: {err_shift:.1f})")
    assert err <= 0.51
    assert err_shift > 3.0
    # Sky above the horizon is smooth and textureless.
    sky = img[:150]
    assert np.abs(np.diff(sky, axis=1)).max() < 2.0 / 255
    # 2x2 supersampling averages the four sub-pixel ground samples.
    img2 = syn.render_frame(drive, i, replace(IDEAL, supersample=2)) / 255.0
    sub = [_pixel_ground_points(drive, i, u + du, v + dv) for du in (-0.25, 0.25) for dv in (-0.25, 0.25)]
    mean = np.mean([drive.ground_intensity(*p) for p in sub], 0)
    err2 = np.abs(img2[v.astype(int), u.astype(int)] - mean).max() * 255
    print(f"supersampled: max error {err2:.2f} grey levels")
    assert err2 <= 0.51


def test_rendered_pixels_show_their_ground_point_over_crests_and_sags():
    """``vertical_curves``: the road ahead bends with the slope the IMU feels, and every ground pixel
    shows the point where its ray meets that bent road (an independent ray cast: bisection on the
    road's height). The plane's cast misses those points: the test sees the bend."""
    d = syn.make_drive(seed=0, duration=20.0, noise=False, render=False, vertical_curves=True)
    t = d.frame_stamps - d.imu_stamps[0]
    # the slope the IMU feels is the road's: the hills' slope steps are in the drive's road slope
    flat = syn.make_drive(seed=0, duration=20.0, noise=False, render=False)
    hills = d._motion.hills(d._motion.distance(t))
    assert np.abs(hills).max() > math.radians(1.0) and flat.road_profile is None
    np.testing.assert_allclose(d.road_slope_camber[:, 0] - flat.road_slope_camber[:, 0], hills, atol=1e-12)
    # the profile the images bend by is that slope, at each frame's distance
    profile = d.road_profile
    np.testing.assert_allclose(np.interp(profile.frame_distance, profile.distance, profile.slope), hills, atol=1e-5)
    # the frame whose road 15 m ahead is furthest from the plane
    bend = [float(profile.height_ahead(sk)(np.array([15.0]))[0][0]) for sk in profile.frame_distance]
    i = int(np.argmax(np.abs(bend)))
    assert abs(bend[i]) > 0.03  # m: a bend the camera sees (~2 px at 15 m)
    height = profile.height_ahead(float(profile.frame_distance[i]))
    img = syn.render_frame(d, i, IDEAL).astype(np.float64) / 255.0
    rng = np.random.default_rng(0)
    v = rng.integers(200, d.camera.height_px, 300).astype(np.float64)  # from ~75 m ahead to the bonnet
    u = rng.integers(0, d.camera.width, 300).astype(np.float64)
    T = syn.camera_poses_4x4(d)[i]
    rays = T[:3, :3] @ np.linalg.solve(d.camera.K.double().numpy(), np.stack([u, v, np.ones_like(u)]))
    x, y, yaw = d.poses_xy_yaw[i]
    ahead = lambda lam: (T[0, 3] + lam * rays[0] - x) * math.cos(yaw) + (T[1, 3] + lam * rays[1] - y) * math.sin(yaw)
    above = lambda lam: T[2, 3] + lam * rays[2] - height(ahead(lam))[0]  # the ray's height over the road
    lo, hi = np.zeros_like(u), -T[2, 3] / rays[2]
    for _ in range(20):  # past the road, whichever way it bends
        hi = np.where(above(hi) > 0, 2 * hi, hi)
    assert (above(hi) <= 0).all()
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = np.where(above(mid) > 0, mid, lo), np.where(above(mid) > 0, hi, mid)
    truth = d.ground_intensity(T[0, 3] + lo * rays[0], T[1, 3] + lo * rays[1])
    err = np.abs(img[v.astype(int), u.astype(int)] - truth).max() * 255
    gx, gy = _pixel_ground_points(d, i, u, v)
    err_plane = np.abs(img[v.astype(int), u.astype(int)] - d.ground_intensity(gx, gy)).max() * 255
    print(f"\nframe {i}: road 15 m ahead {bend[i] * 100:+.1f} cm against the plane; 300 ground pixels: max |pixel - "
          f"ground intensity| {err:.2f} grey levels (the plane's points: {err_plane:.1f})")
    assert err <= 0.51
    assert err_plane > 3.0
    with pytest.raises(ValueError, match="vertical_curves and traffic"):
        syn.make_drive(seed=0, duration=1.0, render=False, vertical_curves=True, traffic=True)


def test_road_profile_heights_ahead():
    """``RoadProfile.height_ahead``: a slope growing by k per metre (a crest of radius 1/k) is the
    parabola ``-k u^2 / 2`` under the base's plane, exactly (the slope is piecewise linear), behind
    the base too; past the profile's ends the slope is held (the road goes on straight)."""
    k, g0 = 1.0 / 900.0, math.radians(-1.0)
    s = np.linspace(0.0, 200.0, 81)
    profile = syn.RoadProfile(s, g0 + k * s, np.array([50.0]))
    z, dz = profile.height_ahead(50.0)(np.array([-20.0, 0.0, 7.5, 12.5, 17.5]))
    u = np.array([-20.0, 0.0, 7.5, 12.5, 17.5])
    np.testing.assert_allclose(z, -k * u**2 / 2, atol=1e-12)
    np.testing.assert_allclose(dz, -k * u, atol=1e-12)
    # beyond the end (s = 200): the slope held at g0 + 200 k, the height continues linearly
    z_end, dz_end = profile.height_ahead(190.0)(np.array([10.0, 30.0]))
    np.testing.assert_allclose(dz_end, [-k * 10.0, -k * 10.0], atol=1e-12)
    np.testing.assert_allclose(z_end, [-k * 50.0, -k * 50.0 - k * 10.0 * 20.0], atol=1e-12)
    with pytest.raises(ValueError, match="increasing"):
        syn.RoadProfile(np.array([0.0, 0.0]), np.zeros(2), np.zeros(1))


def test_true_bev_matches_the_rendered_image(drive):
    """Project BEV cell centres into the rendered image: the picture agrees with true_bev."""
    import cv2

    i = 120
    img = syn.render_frame(drive, i, syn.RenderOptions(noise_std=0.0, vignette=0.0)).astype(np.float32) / 255
    cam = drive.camera.to(dtype=torch.float64)
    p, r = drive.pitch_roll_road[i]
    R, t = camera_pose_on_road(cam, torch.tensor([p]), torch.tensor([r]))
    pts = SPEC.ground_points(torch.float64).reshape(-1, 2)
    ground = torch.cat([pts, torch.zeros(len(pts), 1, dtype=torch.float64)], 1)
    pc = (ground - t) @ R[0]  # road -> camera
    uvw = pc @ cam.K.T
    uv = (uvw[:, :2] / uvw[:, 2:]).numpy().astype(np.float32).reshape(SPEC.size, SPEC.size, 2)
    bev_img = cv2.remap(img, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR)
    bev = syn.true_bev(drive, SPEC, frame=i, supersample=2).numpy()
    diff = np.abs(bev_img - bev)
    corr = np.corrcoef(bev_img.ravel(), bev.ravel())[0, 1]
    print(f"\nBEV from image vs true BEV: mean |diff| {diff.mean():.4f}, corr {corr:.4f}, bev std {bev.std():.3f}")
    assert corr > 0.9 and diff.mean() < 0.03
    # A 1-pixel (10 cm) error in the pose would be visible: the comparison is sharp.
    shifted = syn.ground_patch(*(drive.poses_xy_yaw[i] + [0.1, 0.0, 0.0]), SPEC, drive.ground, supersample=2).numpy()
    corr_shift = np.corrcoef(bev_img.ravel(), shifted.ravel())[0, 1]
    print(f"with a 10 cm pose error: corr {corr_shift:.4f}")
    assert corr_shift < corr - 0.05


def test_ground_patch_conventions(drive):
    x, y, yaw = 3.0, -2.0, 0.0
    mpp = SPEC.metres_per_pixel
    base = syn.ground_patch(x, y, yaw, SPEC)
    fwd = syn.ground_patch(x + mpp, y, yaw, SPEC)
    left = syn.ground_patch(x, y + mpp, yaw, SPEC)
    e_fwd = (fwd[1:] - base[:-1]).abs().max().item()
    e_left = (left[:, 1:] - base[:, :-1]).abs().max().item()
    print(f"\nforward 1 px -> rows shift down (err {e_fwd:.1e}); left 1 px -> cols shift right (err {e_left:.1e})")
    assert base.shape == (SPEC.size, SPEC.size) and base.dtype == torch.float32
    assert e_fwd < 1e-5 and e_left < 1e-5
    assert (fwd - base).abs().mean() > 0.01
    # Rotating by 90 deg left: the BEV's forward axis points along world +y.
    rot = syn.ground_patch(0.0, 0.0, math.pi / 2, SPEC)
    gp = SPEC.ground_points(torch.float64)
    direct = syn.ground_intensity(-gp[..., 1].numpy(), gp[..., 0].numpy())
    assert np.abs(rot.numpy() - direct).max() < 1e-6
    # Batched poses, drive frames and the pose form of true_bev agree.
    poses = drive.poses_xy_yaw[[3, 50]]
    batch = syn.ground_patch(poses[:, 0], poses[:, 1], poses[:, 2], SPEC, drive.ground)
    assert batch.shape == (2, SPEC.size, SPEC.size)
    assert torch.equal(batch[1], syn.true_bev(drive, SPEC, frame=50))
    assert torch.equal(syn.true_bev(np.array([x, y, yaw]), SPEC), base)


def test_texture_is_rich_and_not_repeating():
    g = syn.default_ground(0)
    spec = BevSpec(size=100, metres_per_pixel=0.1, forward_offset=0.0)
    ref = syn.ground_patch(0.0, 20.0, 0.3, spec).numpy()  # away from the lane markings

    def ncc(a, b):
        a, b = a - a.mean(), b - b.mean()
        return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))

    offsets = [1.0, 5.0, 12.8, 25.6, 40.0]
    nccs = [ncc(ref, syn.ground_patch(dx, 20.0, 0.3, spec).numpy()) for dx in offsets]
    fine = syn.ground_patch(0.0, 20.0, 0.3, BevSpec(size=100, metres_per_pixel=0.025, forward_offset=0.0)).numpy()
    grad = np.abs(np.diff(fine, axis=1)).mean()
    vals = g.intensity(np.random.default_rng(1).uniform(-500, 500, 200000), np.random.default_rng(2).uniform(-500, 500, 200000))
    print(f"\nBEV std {ref.std():.3f}, mean grad at 2.5 cm {grad:.4f}; NCC at offsets {offsets} m: {np.round(nccs, 3)}")
    print(f"intensity over 1 km^2: min {vals.min():.3f} max {vals.max():.3f} mean {vals.mean():.3f}")
    assert ref.std() > 0.04 and grad > 0.005
    assert max(abs(c) for c in nccs) < 0.3
    assert vals.min() >= 0.0 and vals.max() <= 1.0


def test_bad_input_raises():
    with pytest.raises(ValueError, match="integer"):
        syn.make_drive(imu_rate=100.0, frame_rate=30.0, render=False)
    with pytest.raises(ValueError, match="duration"):
        syn.make_drive(duration=0.0, render=False)
    with pytest.raises(ValueError, match="render"):
        syn.make_drive(duration=1.0, render="yes")
    with pytest.raises(ValueError, match="speed_range"):
        syn.make_drive(duration=1.0, speed_range=(10.0, 5.0), render=False)
    with pytest.raises(ValueError, match="noise"):
        syn.make_drive(duration=1.0, noise="loud", render=False)
    with pytest.raises(ValueError, match="pose"):
        syn.true_bev(np.zeros(2), SPEC)
    with pytest.raises(ValueError, match="same shape"):
        syn.ground_intensity(np.zeros(3), np.zeros(4))
    d = syn.make_drive(duration=1.0, render=False)
    with pytest.raises(ValueError, match="out of range"):
        syn.render_frame(d, d.num_frames)


def test_options_rates_camera_and_rigid_body():
    d = syn.make_drive(seed=4, duration=1.0, frame_rate=20.0, imu_rate=200.0, bumps=0.0, noise=False,
                       render=False, t0=5.5, camera=syn.kitti_like_camera(mount_pitch=0.01))
    print(f"\n200 Hz IMU / 20 Hz frames: {len(d.imu_stamps)} samples, {d.num_frames} frames, first {d.frame_stamps[0]}")
    assert len(d.imu_stamps) == 201 and d.num_frames == 21 and d.frame_stamps[0] == 5.5
    assert np.array_equal(d.frame_stamps, d.imu_stamps[::10])
    assert np.abs(d.imu_pitch_roll_road).max() == 0.0  # bumps=0: rigid body flat on the road
    # A positive mounting pitch looks down: the optical axis has a negative base-z component.
    axis = d.camera.T_base_cam[:3, 2]
    assert axis[2].item() == pytest.approx(-math.sin(0.01)) and axis[0].item() > 0.99
    assert np.allclose(syn.camera_poses_4x4(d)[:, 2, 3], d.camera.mount_height, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Presets: named deterministic manoeuvres (issue 9), each checked on its defining property
# ---------------------------------------------------------------------------------------------

G = np.array([0.0, 0.0, syn.GRAVITY])


def _kinematic_accel(d: syn.SyntheticDrive) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle acceleration from the noise-free IMU, along and left of the heading (gravity frame). -> 2 x (N,)"""
    a = np.einsum("nij,nj->ni", d.imu_rotation_gravity, d.accel_true) - G
    yaw = d.imu_poses_xy_yaw[:, 2]
    c, s = np.cos(yaw), np.sin(yaw)
    return c * a[:, 0] + s * a[:, 1], -s * a[:, 0] + c * a[:, 1]


def _rel_t(d: syn.SyntheticDrive) -> np.ndarray:
    return d.imu_stamps - d.imu_stamps[0]


def test_presets_listed_deterministic_and_checked():
    assert set(syn.PRESETS) == {"curve", "braking", "bend_start", "stop_and_go", "bumpy", "on_ramp", "urban",
                                "traffic_light", "highway", "parking"}
    assert all(isinstance(v, str) and len(v) > 20 for v in syn.PRESETS.values())
    a = syn.make_drive(seed=3, preset="curve", duration=3.0, render=False)
    b = syn.preset_drive("curve", seed=3, duration=3.0, render=False)
    c = syn.make_drive(seed=4, preset="curve", duration=3.0, render=False)
    for name in ("gyro", "accel", "poses_xy_yaw", "pitch_roll_road", "relative_motion"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for name in ("gyro", "accel", "poses_xy_yaw", "pitch_roll_road"):
        assert not np.allclose(getattr(a, name), getattr(c, name)), name  # the seed still draws the extras
    # ... but not the manoeuvre: same speeds and same planar motion between frames.
    assert np.array_equal(a.speed, c.speed) and np.allclose(a.relative_motion, c.relative_motion, atol=1e-9)
    assert syn.make_drive(preset="braking", render=False).imu_stamps[-1] - 1000.0 == pytest.approx(8.0)
    with pytest.raises(ValueError, match="preset"):
        syn.make_drive(preset="drift", render=False)


def test_preset_curve():
    """100 m radius at 15 m/s: 2.25 m/s^2 and 0.15 rad/s in the sustained part (t = 4..12 s)."""
    rigid = syn.make_drive(seed=1, preset="curve", bumps=0.0, road_tilt=False, noise=False, render=False)
    d = syn.make_drive(seed=1, preset="curve", noise=False, render=False)
    k = (_rel_t(d) >= 4.0) & (_rel_t(d) <= 12.0)
    e_acc = np.abs(rigid.accel_true[k] - [0.0, 2.25, syn.GRAVITY]).max()
    e_gyro = np.abs(rigid.gyro_true[k] - [0.0, 0.0, 0.15]).max()
    _, lat = _kinematic_accel(d)
    fk = (d.frame_stamps - d.frame_stamps[0] >= 4.0) & (d.frame_stamps - d.frame_stamps[0] <= 11.9)
    curv = d.relative_motion[fk[:-1], 2] / np.linalg.norm(d.relative_motion[fk[:-1], :2], axis=1)
    print(f"\ncurve, rigid and flat: accel error {e_acc:.1e} m/s^2, gyro error {e_gyro:.1e} rad/s; with suspension "
          f"and road tilt: lateral {lat[k].mean():.4f} m/s^2 (std {lat[k].std():.3f}), gyro z {d.gyro_true[k, 2].mean():.4f} "
          f"rad/s, radius from the poses {1 / curv.mean():.2f} m; first 2 s max |gyro z| {np.abs(d.gyro_true[:200, 2]).max():.4f}")
    assert e_acc < 1e-6 and e_gyro < 1e-8
    assert lat[k].mean() == pytest.approx(2.25, rel=0.01) and d.gyro_true[k, 2].mean() == pytest.approx(0.15, rel=0.01)
    assert np.allclose(1.0 / curv, 100.0, rtol=1e-3)
    assert np.abs(d.gyro_true[:150, 2]).max() < 0.01  # straight before the entry
    assert np.all(np.abs(np.diff(rigid.gyro_true[:, 2])) < 0.01)  # entered smoothly: no step in the yaw rate


def test_preset_braking():
    """15 m/s, then -5 m/s^2 with a smooth onset, down to 2 m/s, held."""
    d = syn.make_drive(seed=2, preset="braking", noise=False, render=False)
    lon, lat = _kinematic_accel(d)
    t = _rel_t(d)
    onset = t[np.argmax(lon < -4.95)] - t[np.argmax(lon < -0.05)]
    print(f"\nbraking: min longitudinal accel {lon.min():.3f} m/s^2, onset (-0.05 -> -4.95) {onset:.2f} s, "
          f"speed {d.speed[0]:.1f} -> {d.speed[-1]:.2f} m/s, nose-down pitch {np.degrees(d.pitch_roll_road[:, 0].max()):.2f} deg")
    assert lon.min() == pytest.approx(-5.0, abs=0.1)
    assert 0.3 <= onset <= 0.55
    assert d.speed[0] == pytest.approx(15.0) and d.speed[-1] == pytest.approx(2.0) and d.speed.min() > 1.99
    assert np.abs(lon[t > 5.2]).max() < 0.1 and np.abs(lat).max() < 0.5  # holds, straight
    # Load transfer: the suspension pitches the nose down while braking (positive pitch = nose down).
    rigid_free = syn.make_drive(seed=2, preset="braking", road_tilt=False, noise=False, render=False)
    hard = (t > 2.6) & (t < 4.5)
    assert (rigid_free.imu_pitch_roll_road[hard, 0].mean() - rigid_free.imu_pitch_roll_road[t < 1.9, 0].mean()) > np.radians(1.0)


def test_preset_bend_start():
    """The first IMU sample is already in the bend: centripetal acceleration v * wz at sample 0."""
    rigid = syn.make_drive(seed=3, preset="bend_start", bumps=0.0, road_tilt=False, noise=False, render=False)
    d = syn.make_drive(seed=3, preset="bend_start", noise=False, render=False)
    _, lat = _kinematic_accel(d)
    v0, wz0 = d.speed[0], d.gyro_true[0, 2]
    acc_roll = math.degrees(math.atan2(d.accel_true[0, 1], d.accel_true[0, 2]))
    print(f"\nbend start: speed {v0:.1f} m/s, gyro z {wz0:.4f} rad/s, lateral {lat[0]:.4f} m/s^2 (v wz {v0 * wz0:.4f}), "
          f"rigid accel y {rigid.accel_true[0, 1]:.4f}; accelerometer roll {acc_roll:.1f} deg vs true "
          f"{math.degrees(d.imu_pitch_roll_gravity[0, 1]):.1f} deg")
    assert abs(wz0) > 0.15 and rigid.gyro_true[0, 2] == pytest.approx(0.18, abs=1e-8)
    assert rigid.accel_true[0, 1] == pytest.approx(12.0 * 0.18, abs=1e-6)
    assert lat[0] == pytest.approx(v0 * wz0, rel=0.02)
    assert abs(acc_roll - math.degrees(d.imu_pitch_roll_gravity[0, 1])) > 8.0  # the trap: gravity-only roll is far off
    assert np.abs(d.gyro_true[_rel_t(d) > 5.5, 2]).max() < 0.01  # leaves the bend


def test_preset_stop_and_go():
    """Down to 0.1 m per 10 Hz frame (and one full stop) and up again, several times; never reversing."""
    d = syn.make_drive(seed=4, preset="stop_and_go", noise=False, render=False)
    step = np.linalg.norm(d.relative_motion[:, :2], axis=1)
    v = d.speed
    slow = v < 1.0 + 1e-9
    dips = int(np.sum(slow[1:] & ~slow[:-1]))
    print(f"\nstop and go: speed {v.min():.2f}..{v.max():.2f} m/s, {dips} dips to <= 1 m/s, min step "
          f"{step.min():.4f} m/frame, {int((step < 1e-9).sum())} frames standing; forward motion "
          f"{d.relative_motion[:, 0].min():.2e}..{d.relative_motion[:, 0].max():.2f} m")
    assert step.min() <= 0.1 + 1e-9 and dips >= 3 and v.max() >= 8.9
    assert v.min() == 0.0 and (step < 1e-9).sum() >= 15  # one full stop of ~2 s
    assert d.relative_motion[:, 0].min() >= 0.0  # never backwards
    assert np.all(d._motion.speed(np.linspace(-3.0, 50.0, 100001)) >= 0.0)
    assert ((step > 0.099) & (step < 0.101)).sum() >= 10  # holds at 0.1 m/frame


def test_preset_parking_reverses():
    """The one preset that reverses: a stop, 1.5 m/s backwards through a 29 deg turn (the yaw rate's
    sign with the speed's: the heading turns as a car's does backing into a bay), a stop, forward."""
    d = syn.make_drive(seed=4, preset="parking", noise=False, render=False)
    fwd = d.relative_motion[:, 0]
    back = fwd < -0.1
    standing = np.abs(fwd) < 1e-9
    stops = int(np.sum(standing[1:] & ~standing[:-1]))
    turn = math.degrees(d.relative_motion[back, 2].sum())
    print(f"\nparking: backwards {-fwd[back].sum():.2f} m over {back.sum()} frames, turning {turn:+.1f} deg; "
          f"{stops} stops; speed {d.speed.min():.2f}..{d.speed.max():.2f} m/s")
    assert d.speed.min() == pytest.approx(-1.5) and d.speed.max() == pytest.approx(4.0)
    assert back.sum() >= 40 and fwd[back].min() == pytest.approx(-0.15, abs=1e-6)
    assert stops == 2 and standing.sum() >= 30
    assert turn == pytest.approx(-28.6, abs=0.5)  # -0.2 rad/s for 2.5 s (ramps included)
    assert fwd[-1] == pytest.approx(0.3, abs=1e-6)  # forward again at 3 m/s
    with pytest.raises(ValueError, match="reverses"):  # other cars follow the path forwards
        syn.make_drive(seed=4, preset="parking", traffic=True, render=False)
    moved = np.abs(fwd) > 0.01
    assert np.all(np.abs(d.relative_motion[moved, 1]) < 0.02)  # no sideslip either way


def test_the_road_stands_still_under_a_car_at_rest():
    """The road's grade and banking pass under a moving car; at a light they stay as they are: at
    rest the gyro reads nothing and the gravity attitude holds (the slope's and camber's sines run
    on the road's clock, ``_RoadClock``). Moving at a steady speed the clock is time itself (the
    drives without a stop are as before)."""
    d = syn.make_drive(seed=2, preset="traffic_light", noise=False, render=False)
    rest = np.flatnonzero(np.abs(d.speed) < 1e-9)
    assert rest.size > 100  # 15 s at rest
    k = d.frame_imu_index[rest]
    print(f"\nat rest: |gyro| max {np.abs(d.gyro_true[k]).max():.1e} rad/s, gravity attitude moved "
          f"{np.degrees(np.ptp(d.pitch_roll_gravity[rest], axis=0))} deg; moving it turns "
          f"{np.degrees(np.ptp(d.road_slope_camber, axis=0))} deg")
    assert np.abs(d.gyro_true[k]).max() < 1e-8 and np.ptp(d.pitch_roll_gravity[rest], axis=0).max() < 1e-9
    assert np.ptp(d.road_slope_camber[:, 0]) > math.radians(0.05)  # the grade changes while it moves
    assert d._motion.road_clock is not None
    assert syn.make_drive(seed=2, preset="curve", render=False)._motion.road_clock is None  # 15 m/s throughout


def test_preset_bumpy():
    """Suspension and vibration scaled up against the default drive of the same seed, gentle curves."""
    d = syn.make_drive(seed=5, preset="bumpy", render=False)
    ref = syn.make_drive(seed=5, duration=20.0, render=False)
    sd, sr = np.degrees(d.pitch_roll_road.std(0)), np.degrees(ref.pitch_roll_road.std(0))
    vib = (d.accel - d.accel_true - d.accel_bias).std(0)
    vib_ref = (ref.accel - ref.accel_true - ref.accel_bias).std(0)
    print(f"\nbumpy: road-relative pitch/roll std {sd.round(2)} deg (default drive {sr.round(2)}), accel noise std "
          f"{vib.round(2)} m/s^2 (default {vib_ref.round(2)}), speed {d.speed.min():.1f}..{d.speed.max():.1f} m/s, "
          f"max |yaw rate| {np.abs(d.gyro_true[:, 2]).max():.3f} rad/s")
    assert np.all(sd > 1.5 * sr)
    assert np.all(vib > 1.5 * vib_ref)
    assert 6.5 < d.speed.min() and d.speed.max() < 10.5 and np.abs(d.gyro_true[:, 2]).max() < 0.12


def test_preset_on_ramp():
    """A highway on-ramp: 20 deg/s and 3.7 m/s^2 in a 30 m radius, 98 deg of turn, then speeding up."""
    d = syn.make_drive(seed=6, preset="on_ramp", noise=False, render=False)
    _, lat = _kinematic_accel(d)
    turn = np.degrees(np.unwrap(d.poses_xy_yaw[:, 2])[-1] - d.poses_xy_yaw[0, 2])
    k = (_rel_t(d) > 1.2) & (_rel_t(d) < 5.2)
    print(f"\non-ramp: turn {turn:.1f} deg, yaw rate {d.gyro_true[k, 2].mean():.3f} rad/s, lateral {lat[k].mean():.2f} "
          f"m/s^2, speed {d.speed[0]:.1f} -> {d.speed[-1]:.1f} m/s")
    assert turn == pytest.approx(98.0, abs=2.0)
    assert d.gyro_true[k, 2].mean() == pytest.approx(0.35, rel=0.02) and lat[k].mean() == pytest.approx(3.7, rel=0.03)
    assert d.speed[0] == pytest.approx(10.5) and d.speed[-1] == pytest.approx(15.0)


def test_preset_urban():
    """Two 90 deg turns (right, then left), braking for both, the second from 0.1 m per frame."""
    d = syn.make_drive(seed=7, preset="urban", noise=False, render=False)
    yaw = np.degrees(np.unwrap(d.poses_xy_yaw[:, 2]) - d.poses_xy_yaw[0, 2])
    step = np.linalg.norm(d.relative_motion[:, :2], axis=1)
    t = d.frame_stamps - d.frame_stamps[0]
    print(f"\nurban: yaw after the first turn {yaw[np.argmin(np.abs(t - 12.0))]:.1f} deg, at the end {yaw[-1]:.1f} deg, min step "
          f"{step.min():.3f} m/frame, distance {step.sum():.0f} m")
    assert yaw[np.argmin(np.abs(t - 12.0))] == pytest.approx(-90.0, abs=1.0) and yaw[-1] == pytest.approx(0.0, abs=1.0)
    assert step.min() == pytest.approx(0.1, abs=0.002) and np.all(d.relative_motion[:, 0] > 0)


def test_traffic_vehicles_follow_the_drive_and_show_in_the_images():
    """A car ahead drives the ego's path ``headway`` s ahead plus a standing gap (it stops first and
    stands ``standing_gap`` ahead), parked cars stand still, oncoming cars come the other way; the
    renderer shows them (and their shadows) and nothing else changes (IMU, ground truth)."""
    opts = syn.TrafficOptions()
    plain = syn.make_drive(seed=3, preset="traffic_light", noise=False, render=False)
    d = syn.make_drive(seed=3, preset="traffic_light", noise=False, render=False, traffic=opts)
    np.testing.assert_array_equal(d.gyro, plain.gyro)
    np.testing.assert_array_equal(d.poses_xy_yaw, plain.poses_xy_yaw)
    assert plain.traffic is None and len(d.traffic) == d.num_frames
    lead = np.stack([v[0] for v in d.traffic])  # the first row is the car ahead
    gap = np.hypot(*(lead[:, :2] - d.poses_xy_yaw[:, :2]).T) - lead[:, 3] / 2
    still = d.speed < 0.01
    ahead = int(round(opts.headway * 10))  # frames: the car ahead does now what the ego does then
    stopped = still & np.concatenate([still[ahead:], np.zeros(ahead, bool)])
    assert stopped.sum() > 10
    np.testing.assert_allclose(gap[stopped], opts.standing_gap, atol=0.02)
    moving = d.speed > 5.0
    assert (gap[moving] > opts.standing_gap + 0.8 * opts.headway * d.speed[moving] - 0.5).all()
    rest = [v[1:] for v in d.traffic]
    parked = [r[np.abs(((r[:, 2] - d.poses_xy_yaw[k, 2] + math.pi) % (2 * math.pi)) - math.pi) < 0.5]
              for k, r in enumerate(rest)]
    oncoming = [r[np.abs(((r[:, 2] - d.poses_xy_yaw[k, 2]) % (2 * math.pi)) - math.pi) < 0.5]
                for k, r in enumerate(rest)]
    assert sum(len(p) for p in parked) > 0 and sum(len(o) for o in oncoming) > 0
    # The car ahead in the image: the pixels on its rear differ from the empty road's, the sky doesn't.
    cam = syn.kitti_like_camera(scale=0.5)
    k = int(np.argmax(stopped))
    ego = d.poses_xy_yaw[k]
    only_lead = d.traffic[k][:1]
    with_car = syn.render_view(d.ground, cam, ego, d.pitch_roll_road[k], IDEAL, vehicles=only_lead)
    without = syn.render_view(d.ground, cam, ego, d.pitch_roll_road[k], IDEAL)
    diff = np.abs(with_car.astype(int) - without.astype(int)) > 2
    h, w = diff.shape
    # The rear (1.8 m wide, 0.3-1.5 m up at ~6.5 m + 1.08 m camera offset) covers the image centre.
    assert diff[int(0.55 * h):int(0.8 * h), int(0.45 * w):int(0.55 * w)].mean() > 0.9
    assert not diff[: int(0.3 * h)].any()  # the sky is never the car's (it is lower than the camera)
    with pytest.raises(ValueError, match="finite"):
        syn.render_view(d.ground, cam, ego, d.pitch_roll_road[k], IDEAL, vehicles=np.zeros((1, 5)))
    with pytest.raises(ValueError, match="parked_fill"):
        syn.TrafficOptions(parked_fill=2.0)
    with pytest.raises(ValueError, match="traffic"):
        syn.make_drive(seed=0, duration=1.0, render=False, traffic="busy")
