"""Standstill: the small motion between raw images (core/standstill.py) and the engine at rest.

At a red light the BEVs still move (the engine's attitude keeps changing, 1.4 cm per 0.01 deg of
BEV pitch change on KITTI) and the yaw gyro's bias keeps turning the heading; the images say
whether the car moved, and then the motion is zero and the bias observed.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from bevo_ros.config import BevoConfig, build_odometry
from bevo_ros.core.geometry import CameraModel, camera_pose_on_road
from bevo_ros.core.odometry import InvalidInputError
from bevo_ros.core.standstill import (CHECK_BELOW, MIN_TEXTURE_SNR, StandstillDetector, downsample, ground_flow_basis,
                                      small_motion, working_factor)
from bevo_ros.core.vehicle_filter import VehicleFilter, VehicleNoise, initial_vehicle_state
from bevo_ros.datasets.kitti import camera_model_from_kitti
from bevo_ros.datasets.rosbag import feed_engine
from bevo_ros.datasets.synthetic import kitti_like_camera, preset_drive
from bevo_ros.datasets.synthetic.render import render_view
from bevo_ros.io.learned_params import load_learned_params
from bevo_ros.config import REPO_ROOT

FUSED = load_learned_params(REPO_ROOT / "params" / "learned_default.yaml")
KITTI_MOUNTING = (0.0270, -0.0177)  # params/kitti.yaml


def half_camera() -> CameraModel:
    return kitti_like_camera(scale=0.5)


def _small(img: np.ndarray, factor: int) -> torch.Tensor:
    return downsample(torch.as_tensor(img), factor)


@pytest.fixture(scope="module")
def scene():
    cam = half_camera()
    d = preset_drive("curve", seed=1, duration=2.0, render="lazy", camera=cam, road_tilt=True)
    f = working_factor(cam.width)
    return cam, d, f, ground_flow_basis(cam, 0.0, 0.0, f)


def test_small_motion_reads_forward_motion_on_rendered_frames(scene):
    """Pairs rendered at known forward motions (the renderer's exact ground): the estimate is the
    motion to 15 % + 1.5 mm inside the linear range, and the detector says at rest only below 1 cm
    per 10 Hz frame (``odometry.standstill_max_speed`` 0.1 m/s)."""
    cam, d, f, basis = scene
    x, y, yaw = d.poses_xy_yaw[5]
    det = StandstillDetector(cam, (0.0, 0.0), 0.1)
    a = render_view(d.ground, cam, (x, y, yaw), (0.0, 0.0), noise_seed=1)
    for k, dx in enumerate([0.0, 0.003, 0.02, 0.05, 0.1]):
        b = render_view(d.ground, cam, (x + dx * math.cos(yaw), y + dx * math.sin(yaw), yaw), (0.0, 0.0),
                        noise_seed=10 + k)
        m = small_motion(_small(a, f), _small(b, f), basis)
        print(f"dx {dx:.3f} m: {m.forward:+.4f} +- {m.forward_std:.4f} m, inliers {m.inliers:.2f}")
        assert abs(m.forward - dx) < 0.15 * dx + 0.0015
        assert det.at_rest(m, 0.1) == (dx < 0.01)
        assert m.texture_snr > 100 and abs(m.near - dx) < 0.2 * dx + 0.003 and abs(m.far - dx) < 0.2 * dx + 0.003
    # Up to CHECK_BELOW (the correlation's reading under which the engine asks): past the fine
    # estimate's linear range it falls towards zero (0.14 m read 0.009 m on a real drive's rendered
    # frames, a false stop); the detector's coarse scale says no.
    det.remember(torch.as_tensor(a))
    for k, dx in enumerate([0.0, 0.005, 0.1, 0.12, 0.14, CHECK_BELOW]):
        b = render_view(d.ground, cam, (x + dx * math.cos(yaw), y + dx * math.sin(yaw), yaw), (0.0, 0.0),
                        noise_seed=20 + k)
        m = det.measure(torch.as_tensor(b))
        print(f"detector dx {dx:.3f} m: fine {m.forward:+.4f}, coarse {m.coarse_forward:+.4f} m")
        assert det.at_rest(m, 0.1) == (dx < 0.01)


def test_small_motion_ignores_rotation_exposure_and_a_moving_object(scene):
    """The car at rest, the camera pitching 0.05 deg, the exposure up 8 %, and a textured car ahead
    covering a fifth of the road region pulling away (3 px up between the frames): still at rest
    (the first robust weights come from the frame difference, so the object is left out rather
    than fitted). The same object on a moving car does not hide the motion."""
    cam, d, f, basis = scene
    x, y, yaw = d.poses_xy_yaw[5]
    a = render_view(d.ground, cam, (x, y, yaw), (0.0, 0.0), noise_seed=1)
    b = render_view(d.ground, cam, (x, y, yaw), (math.radians(0.05), 0.0), noise_seed=2).astype(np.float64)
    b = np.clip(1.08 * b + 3.0, 0, 255)
    car = np.kron(np.random.default_rng(5).uniform(40, 200, (14, 77)), np.ones((4, 4)))[:50, :300]
    a2, b2 = a.astype(np.float64).copy(), b.copy()
    a2[92:142, 160:460] = car
    b2[89:139, 160:460] = car
    share = float(basis.road[92 // f:142 // f, 160 // f:460 // f].sum() / basis.road.sum())
    assert share > 0.2
    for img_a, img_b in ((a, b), (a2, b2)):
        m = small_motion(_small(img_a, f), _small(img_b.astype(np.uint8), f), basis)
        print(f"at rest: {m.forward:+.5f} +- {m.forward_std:.5f} m, inliers {m.inliers:.2f}")
        assert abs(m.forward) < 0.004 and m.forward_std < 0.002
    moved = render_view(d.ground, cam, (x + 0.03 * math.cos(yaw), y + 0.03 * math.sin(yaw), yaw), (0.0, 0.0),
                        noise_seed=3).astype(np.float64)
    moved[89:139, 160:460] = car
    m = small_motion(_small(a2, f), _small(moved.astype(np.uint8), f), basis)
    assert m.forward == pytest.approx(0.03, abs=0.006)


def _forward_warp(img: np.ndarray, cam: CameraModel, attitude: tuple[float, float], dx: float) -> np.ndarray:
    """What the camera sees after the base moved ``dx`` forward: every pixel's ray meets the road
    plane from the moved camera, projected into the first (exact for the road)."""
    H, W = img.shape
    K = cam.K.double().numpy()
    R, t = camera_pose_on_road(cam.to(dtype=torch.float64), torch.tensor([attitude[0]], dtype=torch.float64),
                               torch.tensor([attitude[1]], dtype=torch.float64))
    R, t = R[0].numpy(), t[0].numpy()
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = (np.stack([uu, vv, np.ones_like(uu)], -1) @ np.linalg.inv(K).T) @ R.T
    depth = -t[2] / np.minimum(rays[..., 2], -1e-3)
    ground = t + np.array([dx, 0.0, 0.0]) + depth[..., None] * rays
    p = ((ground - t) @ R) @ K.T
    return cv2.remap(img, (p[..., 0] / p[..., 2]).astype(np.float32), (p[..., 1] / p[..., 2]).astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_small_motion_on_real_kitti_texture(kitti_root):
    """Real road texture (KITTI sequence 06): a frame against itself with sensor noise and a 10 %
    exposure change is at rest; the same frame moved 3 mm / 2 cm / 5 cm over the road reads that
    motion; two consecutive real frames (1.2 m apart) are far from at rest."""
    seq = kitti_root / "odometry" / "sequences" / "06"
    files = sorted((seq / "image_0").glob("*.png"))[:21:20]
    imgs = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files]
    H, W = imgs[0].shape
    cam = camera_model_from_kitti(seq / "calib.txt", kitti_root / "raw" / "2011_09_26", (W, H), mount_height=1.65)
    f = working_factor(W)
    basis = ground_flow_basis(cam, *KITTI_MOUNTING, f)
    det = StandstillDetector(cam, KITTI_MOUNTING, 0.1)
    rng = np.random.default_rng(0)

    def noisy(img, gain=1.0):
        return np.clip(img * gain + rng.normal(0.0, 1.5, img.shape), 0, 255).astype(np.uint8)

    for img in imgs:
        ref = _small(noisy(img.astype(np.float64)), f)
        for gain in (1.0, 1.1):
            m = small_motion(ref, _small(noisy(img.astype(np.float64), gain), f), basis)
            assert abs(m.forward) < 0.001 and det.at_rest(m, 0.1), m
        for dx in (0.003, 0.02, 0.05):
            m = small_motion(ref, _small(noisy(_forward_warp(img, cam, KITTI_MOUNTING, dx).astype(np.float64)), f),
                             basis)
            print(f"real texture, {dx * 100:.1f} cm: {m.forward * 100:+.3f} +- {m.forward_std * 100:.3f} cm")
            assert m.forward == pytest.approx(dx, rel=0.15, abs=0.001)
            assert det.at_rest(m, 0.1) == (dx < 0.01)
    m = small_motion(_small(imgs[0], f), _small(cv2.imread(str(sorted((seq / "image_0").glob("*.png"))[1]),
                                                           cv2.IMREAD_GRAYSCALE), f), basis)
    assert m.forward > 0.05 and not det.at_rest(m, 0.1)


def test_detector_copies_the_previous_image_and_skips_repeated_frames(scene):
    """A caller refilling one buffer per frame: the remembered image is a copy, so the pair is not
    read as identical. A frame repeated bit for bit (a driver resending its last one) is no
    measurement at all."""
    cam, d, f, _ = scene
    det = StandstillDetector(cam, (0.0, 0.0), 0.1)
    x, y, yaw = d.poses_xy_yaw[5]
    buf = torch.as_tensor(render_view(d.ground, cam, (x, y, yaw), (0.0, 0.0), noise_seed=1)).clone()
    det.remember(buf)
    assert det.measure(buf) is None  # the same frame again
    buf.copy_(torch.as_tensor(render_view(d.ground, cam, (x + 0.03 * math.cos(yaw), y + 0.03 * math.sin(yaw), yaw),
                                          (0.0, 0.0), noise_seed=2)))
    m = det.measure(buf)
    assert m.forward == pytest.approx(0.03, abs=0.006) and not det.at_rest(m, 0.1)
    assert StandstillDetector(cam, (0.0, 0.0), 0.0).measure(buf) is None  # disabled
    det.reset()
    assert det.measure(buf) is None  # nothing remembered


def test_the_remembered_copy_is_reused_and_stays_a_copy(scene):
    """Frame after frame the previous image goes into the previous copy's memory (no fresh clone):
    still a copy of a buffer the caller refills, whether the engine runs in inference mode (it does)
    or a tool calls it outside it afterwards."""
    cam, d, f, _ = scene
    det = StandstillDetector(cam, (0.0, 0.0), 0.1)
    x, y, yaw = d.poses_xy_yaw[5]
    views = [torch.as_tensor(render_view(d.ground, cam, (x + s * math.cos(yaw), y + s * math.sin(yaw), yaw),
                                         (0.0, 0.0), noise_seed=k)) for k, s in enumerate((0.0, 0.03, 0.06))]
    buf = views[0].clone()
    with torch.inference_mode():
        det.remember(buf)
    kept = det._prev[0]
    assert kept.data_ptr() != buf.data_ptr() and not kept.is_inference()
    buf.copy_(views[1])
    det.remember(buf)  # outside inference mode now: the same memory, written again
    assert det._prev[0] is kept and torch.equal(kept, views[1])
    buf.copy_(views[2])
    with torch.inference_mode():
        m = det.measure(buf)
        det.remember(buf)
    assert m.forward == pytest.approx(0.03, abs=0.006)  # views[1] -> views[2], not the refilled buffer against itself
    assert det._prev[0] is kept and torch.equal(kept, views[2])


def test_no_texture_is_no_standstill(scene):
    """Without road texture the images cannot tell 1 cm from 10 cm: flat grey under sensor noise,
    and a night road whose texture is 20x weaker than its noise, moving 5 cm, are not at rest (the
    texture's gradient energy over the noise's is below MIN_TEXTURE_SNR); non-finite images give
    no estimate, and the engine refuses them."""
    cam, d, f, basis = scene
    rng = np.random.default_rng(0)
    det = StandstillDetector(cam, (0.0, 0.0), 0.1)
    flat = [np.clip(120 + rng.normal(0, 2.0, (cam.height_px, cam.width)), 0, 255) for _ in range(2)]
    m = small_motion(_small(flat[0], f), _small(flat[1], f), basis)
    print(f"flat: {m.forward * 100:+.2f} +- {m.forward_std * 100:.2f} cm, texture snr {m.texture_snr:.2f}")
    assert m.texture_snr < MIN_TEXTURE_SNR and not det.at_rest(m, 0.1)
    x, y, yaw = d.poses_xy_yaw[5]
    for dx in (0.05, 0.1):
        pair = [render_view(d.ground, cam, (x + s * math.cos(yaw), y + s * math.sin(yaw), yaw), (0.0, 0.0),
                            noise_seed=k).astype(np.float64) for k, s in ((1, 0.0), (2, dx))]
        night = [np.clip(60 + 0.05 * (p - p.mean()) + rng.normal(0, 4.0, p.shape), 0, 255) for p in pair]
        m = small_motion(_small(night[0], f), _small(night[1], f), basis)
        print(f"night road, {dx * 100:.0f} cm: {m.forward * 100:+.2f} cm, texture snr {m.texture_snr:.2f}")
        assert not det.at_rest(m, 0.1)
    nan = flat[1].copy()
    nan[150, 300] = np.nan
    assert math.isnan(small_motion(_small(flat[0], f), _small(nan, f), basis).forward)
    config = BevoConfig()
    odo = build_odometry(config, FUSED, camera=cam)
    with pytest.raises(InvalidInputError, match="NaN"):
        odo.add_image(1.0, (nan / 255.0).astype(np.float32))


def test_an_object_moving_with_the_car_is_no_standstill(scene):
    """Creeping 5 cm per frame behind a truck that keeps its distance: the truck covers 38 % of the
    road region, all its far part, and pulls the whole region's estimate under 1 cm, but the near
    half sees the road move, so the halves disagree and the frame is not taken as at rest."""
    cam, d, f, basis = scene
    x, y, yaw = d.poses_xy_yaw[5]
    truck = np.kron(np.random.default_rng(7).uniform(40, 200, (29, 90)), np.ones((4, 4)))[:116, :360]
    frames = []
    for k, dx in enumerate((0.0, 0.05)):
        img = render_view(d.ground, cam, (x + dx * math.cos(yaw), y + dx * math.sin(yaw), yaw), (0.0, 0.0),
                          noise_seed=k).astype(np.float64)
        img[40:156, 130:490] = truck  # its rear down to ~7 m ahead of the camera, fixed in the image
        frames.append(img)
    share = float(basis.road[40 // f:156 // f, 130 // f:490 // f].sum() / basis.road.sum())
    m = small_motion(_small(frames[0], f), _small(frames[1], f), basis)
    print(f"behind a truck ({share:.0%} of the region): {m.forward * 100:+.2f} cm (near {m.near * 100:+.2f}, "
          f"far {m.far * 100:+.2f})")
    assert share > 0.3 and abs(m.forward) < 0.01  # the whole region alone would say at rest
    assert m.near > 0.02 and not StandstillDetector(cam, (0.0, 0.0), 0.1).at_rest(m, 0.1)


def test_the_threshold_is_a_speed(scene):
    """At 30 frames per second the same 0.1 m/s allows 3.3 mm per frame: 1 cm per frame (0.3 m/s)
    is motion there, while it is at rest at 10 Hz."""
    cam, d, f, basis = scene
    x, y, yaw = d.poses_xy_yaw[5]
    det = StandstillDetector(cam, (0.0, 0.0), 0.1)
    a = render_view(d.ground, cam, (x, y, yaw), (0.0, 0.0), noise_seed=1)
    for dx, at_10hz, at_30hz in ((0.001, True, True), (0.008, True, False)):
        b = render_view(d.ground, cam, (x + dx * math.cos(yaw), y + dx * math.sin(yaw), yaw), (0.0, 0.0), noise_seed=2)
        m = small_motion(_small(a, f), _small(b, f), basis)
        assert (det.at_rest(m, 0.1), det.at_rest(m, 1 / 30)) == (at_10hz, at_30hz), m


def test_filter_at_rest_is_still_and_learns_the_yaw_bias():
    """At rest the filter's motion is exactly zero whatever the correlation says, with the variance
    the threshold leaves, the gyro's yaw increments are its bias, and the tensor form (training)
    is the same computation."""
    f = VehicleFilter(VehicleNoise())
    bias, dt, rest_var = 0.002, 0.1, 0.005**2  # rad/s: a MEMS gyro's bias, 0.11 deg/s
    rng = np.random.default_rng(0)
    sf, st = initial_vehicle_state(), initial_vehicle_state(like=torch.zeros(2, dtype=torch.float64))
    for k in range(100):
        gyro_yaw = bias * dt + rng.normal(0.0, 1e-4)
        rv = rest_var if k >= 10 else 0.0
        kw = dict(forward=0.03 * rng.normal(), forward_var=1e-3, lateral=0.0, lateral_var=1e-4, rotation=0.001,
                  rotation_var=3e-4, quality=0.5)
        a = f.step(sf, dt, gyro_yaw, rest_var=rv, **kw)
        b = f.step(st, dt, torch.full((2,), gyro_yaw, dtype=torch.float64),
                   rest_var=torch.tensor([rv, 0.0], dtype=torch.float64),
                   **{k_: (torch.full((2,), v, dtype=torch.float64)) for k_, v in kw.items()})
        for x, y in zip(a.motion + a.variance, b.motion + b.variance):
            assert float(y[0]) == pytest.approx(x, rel=1e-12, abs=1e-15)
        if rv:
            assert a.motion == (0.0, 0.0, 0.0) and not a.accepted[0]
            assert a.variance[0] == a.variance[1] == rest_var
            assert float(b.motion[2][1]) != 0.0  # the moving twin still turns on the gyro
        sf, st = a.state, b.state
    assert sf.b == pytest.approx(bias, rel=0.05) and abs(sf.v) < 0.01 and abs(sf.a) < 0.05


@pytest.fixture(scope="module")
def light_drive():
    """The traffic_light preset cut at 28 s: braking to a stop at 9 s, 15 s at rest, pulling away."""
    cam = half_camera()
    d = preset_drive("traffic_light", seed=1, duration=28.0, render="lazy", camera=cam, road_tilt=True,
                     imu_rate=10.0)
    return cam, d, [d.image(k) for k in range(d.num_frames)]


def _run(cam, d, images, max_speed: float, gyro_bias_std: float | None = None):
    config = BevoConfig()
    config.odometry.standstill_max_speed = max_speed
    if gyro_bias_std is not None:
        config.filter.gyro_bias_std = gyro_bias_std
    odo = build_odometry(config, FUSED, camera=cam)
    steps = feed_engine(odo, d.imu_stamps, d.gyro, d.accel, d.frame_stamps, lambda k: images[k], trailing=False)
    return odo, steps


def test_engine_stands_still_at_a_light(light_drive):
    """A 10 Hz drive stopping at a light and pulling away: the frames at rest are found (none while
    moving more than 1.5 cm per frame: the 1 cm threshold, read while the car pitches as it stops
    or pulls away), the pose
    neither creeps nor turns while the car stands, and without the check it does (the test can
    fail)."""
    cam, d, images = light_drive
    gt = d.relative_motion
    rest = gt[:, 0] < 1e-4
    assert rest.sum() > 50
    moves = {}
    for max_speed in (0.1, 0.0):
        odo, steps = _run(cam, d, images, max_speed)
        est = np.array([s.motion for s in steps[1:]])
        flagged = np.array([s.standstill for s in steps[1:]])
        creep, turn = float(np.abs(est[rest, 0]).sum()), float(np.degrees(abs(est[rest, 2].sum())))
        moves[max_speed] = (creep, turn)
        print(f"standstill_max_speed {max_speed}: {flagged.sum()} frames at rest of {rest.sum()} true; "
              f"creep {creep * 100:.1f} cm, turn {turn:.3f} deg while standing; counters {odo.counters.standstill}")
        if max_speed > 0:
            print(f"largest true motion of a frame at rest: {gt[flagged, 0].max() * 100:.2f} cm")
            assert flagged[rest].mean() > 0.95 and not flagged[gt[:, 0] > 0.015].any()
            assert odo.counters.standstill == flagged.sum()
            assert creep < 0.01 and turn < 0.05
            assert all(s.twist_linear[0] == 0.0 for s, r in zip(steps[1:], flagged) if r)
            # The direction of travel: forward until the confirmed stop, either while standing,
            # forward again once pulling away passes 1 m/s (odometry.direction_lock).
            direction = [s.direction_of_travel for s in steps[1:]]
            first_stop = int(np.argmax(flagged))
            assert set(direction[:first_stop]) == {"forward"}
            assert all(direction[k] == "either" for k in np.flatnonzero(flagged))
            assert direction[-1] == "forward" and gt[-1, 0] > 0.1
        else:
            assert not flagged.any() and odo.counters.standstill == 0
    assert moves[0.0][0] > 0.05  # without it: centimetres per frame of BEV-pitch noise read as motion


def test_rest_intervals_give_the_pitch_and_roll_gyro_biases(light_drive):
    """At the light the gyro's x and y rates are their biases (MEMS-grade: -0.10 and +0.18 deg/s over
    the stop): estimated from the rest intervals after the first second of the stop, shrunk towards
    zero by 2 s of prior (measured -0.087 and +0.173 deg/s; -0.065 and +0.150 while the synthetic
    road still tilted under the standing car), taken off the DUKF's prediction, the DUKF's gravity
    pitch at the end of the 15 s stop is 0.86 deg off instead of 3.13 (roll 0.61 vs 1.12). Without
    the standstill check and the estimate between stops (``filter.gyro_bias_std`` 0) nothing is
    estimated (the test can fail). With the estimate between stops on (the default), the stop's
    reading is weighed against it: -0.120 and +0.192 deg/s measured, the DUKF's roll / pitch at the
    stop's end 0.39 / 0.76 deg off."""
    cam, d, images = light_drive
    rest = np.flatnonzero(np.r_[False, d.relative_motion[:, 0] < 1e-4])
    true_bias = d.gyro_bias[d.frame_imu_index[rest], :2].mean(0)
    end_error = {}
    for max_speed, bias_std in ((0.1, 0.0), (0.1, None), (0.0, 0.0)):
        odo, steps = _run(cam, d, images, max_speed, bias_std)
        gravity = np.array([[steps[k].rpy[0], steps[k].rpy[1]] for k in rest])  # (roll, pitch) = (x, y)
        err = np.degrees(np.abs(gravity - d.pitch_roll_gravity[rest][:, ::-1]))
        end_error[max_speed, bias_std] = err[-1]
        print(f"standstill_max_speed {max_speed}, gyro_bias_std {bias_std}: gyro bias estimate {np.degrees(odo.gyro_bias)} deg/s "
              f"(true x, y over the stop {np.degrees(true_bias)}); DUKF roll, pitch error at the stop's end {err[-1]} deg")
        if max_speed > 0:
            # 15 s of 0.3 deg/s white noise and the prior's 12 % shrinkage: within 0.03 deg/s
            assert np.abs(np.array(odo.gyro_bias[:2]) - true_bias).max() < np.radians(0.03)
            assert odo.counters.rest_bias_skipped == 0
        else:
            assert odo.gyro_bias[:2] == (0.0, 0.0)
    for with_stops in ((0.1, 0.0), (0.1, None)):
        assert end_error[with_stops][1] < 0.6 * end_error[0.0, 0.0][1]
    assert end_error[0.1, 0.0][0] < 0.85 * end_error[0.0, 0.0][0]


def test_training_replays_the_stops(light_drive):
    """Training replays the engine's filter inputs (OdometryStep.filter_inputs), the frames at rest
    included, to the same motions and variances."""
    from bevo_ros.training.vehicle import replay

    cam, d, images = light_drive
    _, steps = _run(cam, d, images, 0.1)
    assert sum(s.standstill for s in steps) > 50
    m, v = replay(VehicleNoise(**FUSED.vehicle), [s.filter_inputs for s in steps[1:]])
    assert np.abs(m.numpy() - np.array([s.motion for s in steps[1:]])).max() < 1e-9
    published = np.array([np.diag(s.twist_covariance)[[0, 1, 5]] * s.dt**2 for s in steps[1:]])
    rest = np.array([s.standstill for s in steps[1:]])
    assert np.allclose(v.numpy()[rest][:, :2], published[rest][:, :2], rtol=1e-6, atol=0)


def test_a_frozen_camera_at_speed_is_no_standstill(light_drive):
    """A camera whose picture stops updating for three frames while the car does 9.5 m/s (the same
    view with fresh sensor noise, so not caught as a repeated frame): the images say at rest, but
    a car cannot stop within a frame, so none is taken as a standstill (the motion filter's own
    gate then decides, as for any disagreeing frame)."""
    cam, d, images = light_drive
    rng = np.random.default_rng(0)
    frozen = list(images)
    for k in range(20, 23):
        frozen[k] = np.clip(images[19] + rng.normal(0.0, 2.0, images[19].shape), 0, 255).astype(np.uint8)
    _, steps = _run(cam, d, frozen, 0.1)
    gt = d.relative_motion
    assert not any(s.standstill for s in steps[1:30])
    assert steps[20].motion[0] > 0.8 * gt[19, 0] > 0.7  # the first frozen pair: the prediction carries it


@pytest.fixture(scope="module")
def parking_drive():
    """The parking preset: braking to a stop, reversing 7 m with a 29 deg turn, a stop, forward again."""
    cam = half_camera()
    d = preset_drive("parking", seed=1, render="lazy", camera=cam, road_tilt=True, imu_rate=10.0)
    return cam, d, [d.image(k) for k in range(d.num_frames)]


def _segments(gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame pairs reversing faster than 1.1 m/s (0.11 m per frame) and those moving forward as fast."""
    return gt[:, 0] < -0.11, gt[:, 0] > 0.11


def test_the_engine_follows_a_car_reversing_after_a_stop(parking_drive):
    """After the stop the images confirm, the direction is free: the reversing car is followed
    (direction ``reverse`` once its speed passes 1 m/s; its 6.8 m backwards at over 1.1 m/s read to
    15 %: measured 1.5 % short), the stop after it frees the direction again, and forward it goes.
    Without the standstill check the direction stays locked forward and the reversing is read 41 %
    short (the test can fail)."""
    cam, d, images = parking_drive
    gt = d.relative_motion
    back, fwd = _segments(gt)
    assert back.sum() > 30 and fwd.sum() > 60
    for max_speed in (0.1, 0.0):
        odo, steps = _run(cam, d, images, max_speed)
        est = np.array([s.motion for s in steps[1:]])
        direction = np.array([s.direction_of_travel for s in steps[1:]])
        read = est[back, 0].sum() / gt[back, 0].sum()
        print(f"standstill_max_speed {max_speed}: reversing read {read:.3f} of {-gt[back, 0].sum():.2f} m; "
              f"directions while reversing {dict(zip(*np.unique(direction[back], return_counts=True)))}")
        if max_speed > 0:
            assert 0.85 < read < 1.15
            assert (direction[back] == "reverse").mean() > 0.9
            assert direction[-1] == "forward" and est[-1, 0] > 0.2
        else:
            assert read < 0.75 and set(direction) == {"forward"}  # only what DIRECTION_TOLERANCE lets through


def test_a_signed_speed_gives_the_direction_an_unsigned_one_takes_it_from_the_images(parking_drive):
    """A signed speed (wheel odometry in the base frame: negative reversing) sets the direction of
    travel itself: with the standstill check off (the images cannot confirm a stop) the reversing is
    followed, the correlation searching backwards (direction ``reverse``). An unsigned one (a GNSS
    speed over ground, a wheel's magnitude) takes its sign from the images: after the stop they
    confirm, from the correlation's reading, then from the direction of travel. Each lands the drive's
    endpoint within 2 % of its path (measured 1.1 % and 0.7 %). An unsigned speed with no stop confirmed
    stays forward and reads the reversing forwards (measured 45 %: the test can fail)."""
    cam, d, images = parking_drive
    gt = d.relative_motion
    back, _ = _segments(gt)
    mids = 0.5 * (d.frame_stamps[1:] + d.frame_stamps[:-1])
    v = gt[:, 0] / np.diff(d.frame_stamps)
    noise = np.random.default_rng(3).normal(0.0, 0.05, v.size)
    path = float(np.hypot(gt[:, 0], gt[:, 1]).sum())
    for signed, max_speed in ((True, 0.0), (False, 0.1), (False, 0.0)):
        config = BevoConfig()
        config.odometry.standstill_max_speed = max_speed
        odo = build_odometry(config, FUSED, camera=cam)
        speeds = [(float(t), float(s if signed else abs(s)) + float(e), 0.0025, signed)
                  for t, s, e in zip(mids, v, noise)]
        steps = feed_engine(odo, d.imu_stamps, d.gyro, d.accel, d.frame_stamps, lambda k: images[k], trailing=False,
                            speeds=speeds)
        est = np.array([s.motion for s in steps[1:]])
        direction = np.array([s.direction_of_travel for s in steps[1:]])
        drift = float(np.linalg.norm(_endpoint(est) - _endpoint(gt)) / path)
        print(f"signed {signed}, standstill_max_speed {max_speed}: drift {drift * 100:.2f} % of {path:.1f} m; "
              f"directions while reversing {dict(zip(*np.unique(direction[back], return_counts=True)))}")
        if signed or max_speed > 0:
            assert (direction[back] == "reverse").mean() > 0.9 and direction[-1] == "forward"
            assert drift < 0.02
        else:
            assert set(direction) == {"forward"} and drift > 0.2


def test_an_unsigned_speed_behind_a_car_pulling_away_stays_forward():
    """At the light a car ahead pulls away first, which in the BEV moves as the road would if the
    ego reversed. An unsigned speed takes its sign from the correlation after the stop, only once
    that reading is clear of zero: the engine pulls away forward, never ``reverse``, and drifts as
    with a signed speed (measured 0.80 % against 0.75 %; the whole drive, 32 s). The correlation's
    prior and the direction lock hold the car's peak out here even with no margin over zero: the
    test guards the case, it does not single out the 3-sigma margin."""
    cam = half_camera()
    d = preset_drive("traffic_light", seed=1, render="lazy", camera=cam, imu_rate=10.0, traffic=True)
    images = [d.image(k) for k in range(d.num_frames)]
    gt = d.relative_motion
    mids = 0.5 * (d.frame_stamps[1:] + d.frame_stamps[:-1])
    v = gt[:, 0] / np.diff(d.frame_stamps)
    noise = np.random.default_rng(3).normal(0.0, 0.05, v.size)
    path = float(np.hypot(gt[:, 0], gt[:, 1]).sum())
    drift = {}
    for signed in (True, False):
        odo = build_odometry(BevoConfig(), FUSED, camera=cam)
        speeds = [(float(t), abs(float(s) + float(e)), 0.0025, signed) for t, s, e in zip(mids, v, noise)]
        steps = feed_engine(odo, d.imu_stamps, d.gyro, d.accel, d.frame_stamps, lambda k: images[k], trailing=False,
                            speeds=speeds)
        est = np.array([s.motion for s in steps[1:]])
        direction = [s.direction_of_travel for s in steps[1:]]
        drift[signed] = float(np.linalg.norm(_endpoint(est) - _endpoint(gt)) / path)
        print(f"signed {signed}: drift {drift[signed] * 100:.2f} %; directions {sorted(set(direction))}")
        assert "reverse" not in direction and direction[-1] == "forward" and odo.counters.standstill > 50
    assert drift[False] < max(2 * drift[True], 0.01)


def _endpoint(motions: np.ndarray) -> np.ndarray:
    """The (x, y) reached by composing ``(F, 3)`` planar motions (dx, dy, dyaw) from the origin."""
    x = y = th = 0.0
    for dx, dy, dth in motions:
        x, y, th = x + dx * math.cos(th) - dy * math.sin(th), y + dx * math.sin(th) + dy * math.cos(th), th + dth
    return np.array([x, y])
