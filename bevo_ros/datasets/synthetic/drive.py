"""A synthetic drive with exact ground truth (:class:`SyntheticDrive`, :func:`make_drive`,
:func:`preset_drive`): the motion of :mod:`.motion` sampled at the IMU and camera stamps, the IMU
errors of :mod:`.imu`, the ground of :mod:`.ground` along the driven path, frames from :mod:`.render`.

Arrays of a :class:`SyntheticDrive` are numpy (float64 unless stated).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from bevo_ros.core.geometry import CameraModel
from bevo_ros.core.rate_integration import GYRO_SAMPLING
from bevo_ros.datasets.synthetic.ground import RoadGround, _lane_path
from bevo_ros.datasets.synthetic.imu import ImuNoise, noisy_imu
from bevo_ros.datasets.synthetic.motion import (_PRESETS, REVERSING_PRESETS, _integrate_xy, _Motion, _random_hills,
                                                _random_motion, _RoadClock, _with_preset)
from bevo_ros.datasets.synthetic.render import RenderOptions, RoadProfile, kitti_like_camera, render_frame
from bevo_ros.datasets.synthetic.traffic import TrafficOptions, as_traffic_options, traffic_at_frames
from bevo_ros.rotations import rotation_x, rotation_y, rotation_z, rpy_from_matrices

__all__ = ["LazyImages", "SyntheticDrive", "base_poses_4x4", "camera_poses_4x4", "make_drive", "preset_drive"]


# ---------------------------------------------------------------------------------------------
# The drive
# ---------------------------------------------------------------------------------------------


class LazyImages:
    """``(F, H, W)`` uint8 frames rendered on access (``images[i]``, slices, iteration, ``np.asarray``)."""

    def __init__(self, drive: "SyntheticDrive") -> None:
        self._drive = drive

    def __len__(self) -> int:
        return len(self._drive.frame_stamps)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self), self._drive.camera.height_px, self._drive.camera.width)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return np.stack([render_frame(self._drive, k) for k in range(*i.indices(len(self)))])
        return render_frame(self._drive, int(i))

    def __iter__(self):
        return (render_frame(self._drive, k) for k in range(len(self)))

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


@dataclass
class SyntheticDrive:
    """A synthetic drive with exact ground truth. ``F`` frames, ``N`` IMU samples; numpy arrays.

    Stamps are seconds (float64) from ``t0``; frame ``i`` is IMU sample ``frame_imu_index[i]`` and
    ``frame_stamps == imu_stamps[frame_imu_index]`` exactly (:func:`make_drive`; a drive of
    :func:`~bevo_ros.datasets.synthetic.oxts_drive.drive_from_oxts` has its frames on the camera's
    clock and ``frame_imu_index`` the nearest IMU sample).
    """

    camera: CameraModel
    ground: RoadGround
    seed: int
    frame_stamps: np.ndarray  # (F,)
    frame_imu_index: np.ndarray  # (F,) int
    images: np.ndarray | LazyImages | None  # (F, H, W) uint8
    imu_stamps: np.ndarray  # (N,)
    gyro: np.ndarray  # (N, 3) rad/s, base frame, with noise
    accel: np.ndarray  # (N, 3) m/s^2, specific force, base frame, with noise
    gyro_true: np.ndarray  # (N, 3) noise-free
    accel_true: np.ndarray  # (N, 3) noise-free
    gyro_bias: np.ndarray  # (N, 3) the bias contained in gyro
    accel_bias: np.ndarray  # (N, 3) the bias contained in accel
    poses_xy_yaw: np.ndarray  # (F, 3) world x, y (m) and yaw (rad, wrapped to [-pi, pi))
    pitch_roll_road: np.ndarray  # (F, 2) base attitude relative to the road
    pitch_roll_gravity: np.ndarray  # (F, 2) base attitude relative to gravity (what OXTS reports)
    road_slope_camber: np.ndarray  # (F, 2) road tilt against gravity, relative to the heading
    relative_motion: np.ndarray  # (F-1, 3) (dx, dy, dyaw) of the base, frame i-1 -> i, in base frame i-1
    speed: np.ndarray  # (F,) m/s
    base_height: np.ndarray  # (F,) base origin above the road, m
    imu_pitch_roll_road: np.ndarray  # (N, 2)
    imu_pitch_roll_gravity: np.ndarray  # (N, 2)
    imu_road_slope_camber: np.ndarray  # (N, 2)
    imu_rotation_gravity: np.ndarray  # (N, 3, 3) R_grav_base
    imu_velocity_gravity: np.ndarray  # (N, 3) base velocity in the gravity frame, m/s
    imu_poses_xy_yaw: np.ndarray  # (N, 3)
    render_options: RenderOptions = field(default_factory=RenderOptions)
    image_noise: bool = True
    traffic: list[np.ndarray] | None = None  # per frame (K_f, 7) other vehicles (.traffic), or None
    road_profile: RoadProfile | None = None  # crests and sags the images show (None: the road ahead is a plane)
    _motion: _Motion | None = field(default=None, repr=False)

    @property
    def num_frames(self) -> int:
        return len(self.frame_stamps)

    def __repr__(self) -> str:
        images = type(self.images).__name__ if self.images is not None else "None"
        return (f"SyntheticDrive(seed={self.seed}, frames={self.num_frames}, imu={len(self.imu_stamps)}, "
                f"t={self.imu_stamps[0]:.2f}..{self.imu_stamps[-1]:.2f} s, images={images})")

    def ground_intensity(self, x, y):
        """Ground intensity in [0, 1] at world points (see :meth:`RoadGround.intensity`)."""
        return self.ground.intensity(x, y)

    def image(self, index: int) -> np.ndarray:
        """Frame ``index`` as ``(H, W)`` uint8 (from ``images`` if rendered, else rendered now)."""
        if isinstance(self.images, np.ndarray):
            return self.images[index]
        return render_frame(self, index)

    def to_recording(self, frame_range: tuple[int, int] | None = None):
        """The drive as the datasets' one recording type, :class:`bevo_ros.datasets.rosbag.Recording`,
        without a bag: what ``load_sequence(write_drive_bag(drive, frame_range=...))`` gives (same IMU
        span, ground truth relative to the first frame, gravity-referenced attitude), except that stamps
        keep their float64 seconds (a bag rounds them to ns) and the camera is the drive's own.
        Renders every frame in ``frame_range`` (first, stop) unless the images are already arrays."""
        from bevo_ros.datasets.rosbag import Recording

        f0, f1 = frame_range or (0, self.num_frames)
        t_lo, t_hi = self.frame_stamps[f0], self.frame_stamps[f1 - 1]
        imu = (self.imu_stamps >= t_lo - 0.5) & (self.imu_stamps <= t_hi)  # write_drive_bag's span
        poses = base_poses_4x4(self)
        poses = np.linalg.inv(poses[f0]) @ poses[f0:f1]
        images = np.stack([np.asarray(self.image(i)) for i in range(f0, f1)])
        return Recording(
            imu_stamps=torch.from_numpy(self.imu_stamps[imu]),
            gyro=torch.from_numpy(self.gyro[imu]),
            accel=torch.from_numpy(self.accel[imu]),
            frame_stamps=torch.from_numpy(self.frame_stamps[f0:f1].copy()),
            images=torch.from_numpy(images),
            camera=self.camera,
            gt_poses=torch.from_numpy(poses),
            gt_pitch_roll=torch.from_numpy(self.pitch_roll_gravity[f0:f1].copy()),
            name=f"synthetic-seed{self.seed}",
        )


def preset_drive(name: str, seed: int = 0, duration: float | None = None, **kw) -> SyntheticDrive:
    """``make_drive(seed, duration, preset=name, **kw)``: a named drive (see :data:`PRESETS`)."""
    return make_drive(seed, duration, preset=name, **kw)


def _check_positive(**kw) -> None:
    for k, v in kw.items():
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{k} must be a positive finite number, got {v!r}")


def make_drive(
    seed: int = 0,
    duration: float | None = None,
    frame_rate: float = 10.0,
    imu_rate: float = 100.0,
    bumps: float = 1.0,
    road_tilt: bool | tuple[float, float] = True,
    noise: bool | float | ImuNoise = True,
    render: bool | str = True,
    *,
    camera: CameraModel | None = None,
    speed_range: tuple[float, float] = (5.0, 15.0),
    speed_variation: float = 1.0,
    curvature: float = 1.0,
    max_yaw_rate: float = 0.3,
    max_lateral_accel: float = 4.0,
    t0: float = 1000.0,
    start_pose: tuple[float, float, float] | None = None,
    render_options: RenderOptions | None = None,
    ground_seed: int | None = None,
    preset: str | None = None,
    gyro_sampling: str = "interval_mean",
    traffic: TrafficOptions | bool | None = None,
    vertical_curves: bool = False,
    grade: float = 0.0,
) -> SyntheticDrive:
    """Simulate a drive: trajectory, IMU at ``imu_rate`` and camera frames at ``frame_rate``.

    Args:
        seed: everything (motion, noise, texture unless ``ground_seed``) is deterministic by seed.
        duration: seconds (default 20, or the preset's length); frames at ``t0 + k / frame_rate``,
            IMU at ``t0 + k / imu_rate``.
        bumps: scale of the road-relative pitch/roll (suspension oscillation, bump events,
            load transfer). 0 = rigid body flat on the road.
        road_tilt: True = slowly varying slope/camber; False = none; ``(slope, camber)`` radians
            = constant tilt.
        noise: True/False, a scale factor, or an :class:`ImuNoise`. False also gives ideal images
            (no image noise, no vignette).
        render: True = render every frame now into ``images``; "lazy" = ``images`` renders on
            access; False = ``images`` is None (use :func:`render_frame`).
        speed_variation: 0 = constant speed ``mean(speed_range)``; 1 = the full range.
        curvature: scale of the curves' yaw rates; 0 = straight line.
        start_pose: world ``(x, y, yaw)`` at the first frame; default random.
        preset: a named, deterministic manoeuvre (:data:`PRESETS`: ``curve``, ``braking``,
            ``bend_start``, ``stop_and_go``, ``bumpy``, ``on_ramp``, ``urban``, ``traffic_light``,
            ``highway``, ``parking``, the one that reverses): it fixes speed and yaw rate (``speed_range``,
            ``speed_variation``, ``curvature``, ``max_yaw_rate``, ``max_lateral_accel`` are then unused);
            suspension, bumps, road tilt, start pose and noise still follow ``seed`` and the other
            arguments. None = the seeded random drive.
        gyro_sampling: what each gyro sample is: ``"interval_mean"`` (default) the mean rate over
            the interval since the previous sample, as a delta-angle IMU reports it and as the
            KITTI OXTS rates behave (see ``filter.gyro_sampling``); ``"instantaneous"`` the rate
            at the stamp.
        traffic: other vehicles in the images (:mod:`.traffic`): True = the default
            :class:`TrafficOptions` (a car ahead, parked cars, oncoming cars), or options; None/False
            = an empty road. The IMU and the ground truth do not depend on it.
        vertical_curves: seeded crests and sags along the distance travelled (slope steps of
            0.7-2.5 deg over 25-70 m, longer at speed) on top of ``road_tilt``: the IMU feels them
            and the images show the road ahead bent by them (``road_profile``; the BEV's plane is
            no longer the road under the car, as on real roads). The road-relative attitude stays
            the one to the road under the base. Not with ``traffic`` (its vehicles stand on the plane).
        grade: a constant road grade (rad; the pitch's sign, REP-103: positive is nose down, i.e.
            downhill) added to the road's slope (``road_tilt``'s, seeded or given): the IMU feels it,
            the images and the motion on the road do not change (they are relative to the road), so
            a drive's cached frames serve any grade. A cold start on a hill
            (``tools/eval_real_imu.py --grade``).

    Returns:
        a :class:`SyntheticDrive`.
    """
    if preset is not None and preset not in _PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(_PRESETS)}")
    pre_set = _PRESETS[preset] if preset is not None else None
    if duration is None:
        duration = pre_set.duration if pre_set is not None else 20.0
    _check_positive(duration=duration, frame_rate=frame_rate, imu_rate=imu_rate)
    for name, sd in (("seed", seed), ("ground_seed", 0 if ground_seed is None else ground_seed)):
        if isinstance(sd, bool) or not isinstance(sd, (int, np.integer)) or sd < 0:
            raise ValueError(f"{name} must be an integer >= 0, got {sd!r}")
    if not math.isfinite(t0):
        raise ValueError(f"t0 must be finite, got {t0!r}")
    ratio = imu_rate / frame_rate
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ValueError(f"imu_rate / frame_rate must be a positive integer, got {imu_rate} / {frame_rate}")
    step = int(round(ratio))
    if not (len(speed_range) == 2 and 0 < speed_range[0] <= speed_range[1]):
        raise ValueError(f"speed_range must be (min, max) with 0 < min <= max, got {speed_range}")
    for name, v in (("bumps", bumps), ("speed_variation", speed_variation), ("curvature", curvature)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    if gyro_sampling not in GYRO_SAMPLING:
        raise ValueError(f"gyro_sampling must be one of {GYRO_SAMPLING}, got {gyro_sampling!r}")
    traffic = as_traffic_options(traffic)
    if vertical_curves and traffic is not None:
        raise ValueError("vertical_curves and traffic cannot be combined: the vehicles stand on the road's plane")
    if traffic is not None and preset in REVERSING_PRESETS:
        raise ValueError(f"traffic cannot be combined with the {preset!r} preset: the vehicles follow the "
                         "drive's path forwards, and it reverses")
    if not (math.isfinite(float(grade)) and abs(float(grade)) <= 0.35):
        raise ValueError(f"grade must be a finite angle within +-0.35 rad (20 deg), got {grade!r}")
    if render not in (True, False, "lazy"):
        raise ValueError(f"render must be True, False or 'lazy', got {render!r}")
    if not (road_tilt is True or road_tilt is False or (isinstance(road_tilt, (tuple, list)) and len(road_tilt) == 2)):
        raise ValueError(f"road_tilt must be a bool or (slope, camber) in radians, got {road_tilt!r}")
    if isinstance(noise, ImuNoise):
        imu_noise, noisy = noise, True
    elif isinstance(noise, (bool, int, float)):
        if not (math.isfinite(float(noise)) and float(noise) >= 0):
            raise ValueError(f"noise must be a bool, a scale >= 0 or an ImuNoise, got {noise!r}")
        imu_noise, noisy = ImuNoise().scaled(float(noise)), float(noise) > 0
    else:
        raise ValueError(f"noise must be a bool, a scale >= 0 or an ImuNoise, got {noise!r}")
    if pre_set is not None:
        bumps = bumps * pre_set.bumps_gain
        if pre_set.vibration_gain != 1.0:
            imu_noise = replace(imu_noise, accel_vibration=imu_noise.accel_vibration * pre_set.vibration_gain)
    camera = camera if camera is not None else kitti_like_camera()
    options = render_options if render_options is not None else RenderOptions()
    if not noisy:
        options = replace(options, noise_std=0.0, vignette=0.0)

    rng = np.random.default_rng([int(seed), 1])
    if start_pose is None:
        start_pose = (rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-math.pi, math.pi))
    n_imu = int(math.floor(duration * imu_rate + 1e-9)) + 1
    n_frames = (n_imu - 1) // step + 1
    t_imu = np.arange(n_imu) / imu_rate
    pre, post = 3.0, 3.0  # extra seconds of lane path around the drive
    motion = _random_motion(
        rng, -pre, t_imu[-1] + post, speed_range=speed_range, speed_variation=speed_variation,
        curvature=curvature, max_yaw_rate=max_yaw_rate, max_lateral_accel=max_lateral_accel, bumps=bumps,
        road_tilt=road_tilt, camera=camera, start_yaw=float(start_pose[2]),
    )
    if grade:
        motion = replace(motion, slope0=motion.slope0 + float(grade))
    v_ref = speed_range[1]  # vibration envelope: relative to the fastest speed
    if pre_set is not None:
        motion = _with_preset(motion, pre_set, np.random.default_rng([int(seed), 5]), -pre, t_imu[-1] + post, bumps)
    # the road's grade and banking stand still under a car at rest (1 s of margin for the IMU's differences)
    motion = replace(motion, road_clock=_RoadClock.of(motion, -pre - 1.0, t_imu[-1] + post + 1.0))
    if vertical_curves:
        # past the end by the renderer's reach (haze_end), so the last frame sees its road ahead
        span = np.linspace(-pre, t_imu[-1] + post, 2000)
        travelled = motion.distance(span)  # not monotonic where the car reverses
        hills_range = (float(travelled.min()), float(travelled.max()) + options.haze_end)
        v_max = float(np.abs(motion.speed(span)).max())
        motion = replace(motion, hills=_random_hills(np.random.default_rng([int(seed), 7]), *hills_range, v_max))
    # Dense grid (>= 1 kHz, containing every IMU stamp) for the position integral.
    sub = max(1, int(math.ceil(1000.0 / imu_rate)))
    h = 1.0 / (imu_rate * sub)
    j_pre, j_post = int(math.ceil(pre / h)), int(math.ceil(post / h))
    j = np.arange(-j_pre, (n_imu - 1) * sub + j_post + 1)
    t_dense = j * h
    xy_dense = _integrate_xy(motion, t_dense, (float(start_pose[0]), float(start_pose[1])), j_pre)
    xy_imu = xy_dense[j_pre + np.arange(n_imu) * sub]
    if pre_set is not None:
        v_dense = motion.speed(t_dense)
        if v_dense.min() < 0 and not pre_set.reverses:  # a preset bug, never the user's
            raise AssertionError(f"preset {preset!r} reverses (speed {v_dense.min():.3g} m/s)")
        v_ref = float(np.abs(v_dense).max())

    yaw = motion.yaw(t_imu)
    r_grav = motion.r_grav_base(t_imu)
    roll_g, pitch_g, _ = rpy_from_matrices(r_grav)
    pr_road = np.stack([motion.pitch_rel(t_imu), motion.roll_rel(t_imu)], -1)
    tilt = np.stack([motion.slope(t_imu), motion.camber(t_imu)], -1)
    if gyro_sampling == "interval_mean":
        gyro_true = motion.gyro_interval_mean(t_imu, 1.0 / imu_rate)
    else:
        gyro_true = motion.gyro(t_imu)
    accel_true = motion.specific_force(t_imu)
    vel = motion.vel_grav(t_imu)

    gyro, accel = gyro_true.copy(), accel_true.copy()
    gyro_bias, accel_bias = np.zeros_like(gyro), np.zeros_like(accel)
    if noisy:
        gyro, accel, gyro_bias, accel_bias = noisy_imu(gyro_true, accel_true, t_imu, motion.speed(t_imu),
                                                       v_ref, imu_rate, imu_noise, seed)

    fi = np.arange(n_frames) * step
    poses = np.concatenate([xy_imu, ((yaw + math.pi) % (2 * math.pi) - math.pi)[:, None]], 1)
    xy_f, yaw_f = xy_imu[fi], yaw[fi]
    d = xy_f[1:] - xy_f[:-1]
    c, s = np.cos(yaw_f[:-1]), np.sin(yaw_f[:-1])
    rel = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], yaw_f[1:] - yaw_f[:-1]], 1)

    ground = RoadGround(seed if ground_seed is None else ground_seed, path=_lane_path(xy_dense, motion.yaw(t_dense)))
    stamps = float(t0) + t_imu
    drive = SyntheticDrive(
        camera=camera, ground=ground, seed=int(seed), frame_stamps=stamps[fi], frame_imu_index=fi, images=None,
        imu_stamps=stamps, gyro=gyro, accel=accel, gyro_true=gyro_true, accel_true=accel_true,
        gyro_bias=gyro_bias, accel_bias=accel_bias, poses_xy_yaw=poses[fi], pitch_roll_road=pr_road[fi],
        pitch_roll_gravity=np.stack([pitch_g, roll_g], -1)[fi], road_slope_camber=tilt[fi], relative_motion=rel,
        speed=motion.speed(t_imu)[fi], base_height=motion.z_base(t_imu)[fi], imu_pitch_roll_road=pr_road,
        imu_pitch_roll_gravity=np.stack([pitch_g, roll_g], -1), imu_road_slope_camber=tilt,
        imu_rotation_gravity=r_grav, imu_velocity_gravity=vel, imu_poses_xy_yaw=poses,
        render_options=options, image_noise=noisy, _motion=motion,
    )
    if vertical_curves:
        grid = np.arange(hills_range[0], hills_range[1] + 0.25, 0.25)
        drive.road_profile = RoadProfile(grid, motion.hills(grid), motion.distance(t_imu[fi]))
    if traffic is not None:
        drive.traffic = traffic_at_frames(traffic, t_dense, xy_dense, motion.yaw(t_dense), t_imu[fi], seed)
    if render == "lazy":
        drive.images = LazyImages(drive)
    elif render:
        drive.images = np.stack([render_frame(drive, i) for i in range(n_frames)])
    return drive


# ---------------------------------------------------------------------------------------------
# Ground truth helpers
# ---------------------------------------------------------------------------------------------


def base_poses_4x4(drive: SyntheticDrive, at_imu: bool = False) -> np.ndarray:
    """World (road-frame) poses of the base incl. road-relative pitch/roll and height. -> ``(F, 4, 4)``."""
    if at_imu:
        xy_yaw, pr = drive.imu_poses_xy_yaw, drive.imu_pitch_roll_road
        z = drive._motion.z_base(drive.imu_stamps - drive.imu_stamps[0]) if drive._motion else None
    else:
        xy_yaw, pr, z = drive.poses_xy_yaw, drive.pitch_roll_road, drive.base_height
    T = np.tile(np.eye(4), (len(xy_yaw), 1, 1))
    T[:, :3, :3] = rotation_z(xy_yaw[:, 2]) @ rotation_y(pr[:, 0]) @ rotation_x(pr[:, 1])
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = xy_yaw[:, 0], xy_yaw[:, 1], z
    return T


def camera_poses_4x4(drive: SyntheticDrive) -> np.ndarray:
    """World poses of the camera at the frames, ``base_poses_4x4 @ T_base_cam``. -> ``(F, 4, 4)``."""
    return base_poses_4x4(drive) @ drive.camera.T_base_cam.detach().cpu().double().numpy()
