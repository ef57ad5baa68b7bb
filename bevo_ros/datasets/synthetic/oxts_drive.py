"""A real drive's motion and IMU with a rendered camera (:func:`drive_from_oxts`).

The shared KITTI data hold whole drives of OXTS (real IMU through bends, stops and braking, with
the unit's own attitude, velocity and position) but images only for 51 frames. This builds a
:class:`~bevo_ros.datasets.synthetic.drive.SyntheticDrive` whose path, speed and IMU are the real
drive's and whose frames are rendered on the synthetic road: the engine then meets a real car's
dynamics (its suspension, vibration, gyro errors, stops) end to end, over minutes, against a ground
truth that is exact for the rendered camera.

What is real and what is defined here:

- path, heading, speed: the unit's position (KITTI devkit Mercator projection), yaw and velocity;
- IMU: the unit's ``ax..az`` and ``wx..wz`` at its own stamps, one sample per frame (10 Hz);
- frames: on the camera's clock behind the records' jittered stamps (:func:`_camera_clock`), the
  poses interpolated to it;
- the body's pitch on the road (what the camera's BEV needs): the unit's pitch minus the road's
  slope ``atan(vu / v)``, the body's heave on its springs smoothed out of it by a zero-phase
  Gaussian (the reference of ``test_road_pitch_on_real_drives``), held through stops where the
  slope is not observable, its mean removed (the unit's mounting);
- the body's roll on the road: no sensor separates it from the road's camber. A passenger car
  leans out of a bend by 4-6 deg per g (``lean_gradient``, rad per m/s^2 of the centripetal
  ``v wz``), so the roll is that lean plus the unit's roll's fast part; its slow part less the lean
  (a zero-phase Gaussian) is the camber. The rendered roll is an assumption, the pitch is not.

By default the camera renders the locally planar road (no crest ahead). With ``vertical_curves``
the road ahead of each frame bends by the drive's own slope further along (its profile over the
distance travelled, :class:`~bevo_ros.datasets.synthetic.render.RoadProfile`): the crests and sags
the car is about to drive over, as a real camera sees them.
"""
from __future__ import annotations

import math

import numpy as np

from bevo_ros.core.geometry import CameraModel
from bevo_ros.datasets.kitti import OxtsData, bridged_imu, interpolated_oxts, oxts_positions
from bevo_ros.datasets.synthetic.drive import LazyImages, SyntheticDrive
from bevo_ros.datasets.synthetic.ground import RoadGround, _lane_path
from bevo_ros.datasets.synthetic.traffic import TrafficOptions, as_traffic_options, traffic_at_frames
from bevo_ros.datasets.synthetic.render import RenderOptions, RoadProfile, kitti_like_camera, render_frame
from bevo_ros.rotations import rotation_x, rotation_y, rotation_z

__all__ = ["drive_from_oxts"]


def _gaussian_smooth(x: np.ndarray, sigma: float) -> np.ndarray:
    """Zero-phase Gaussian of ``sigma`` samples, edges padded with the end values. ``(N,)`` -> ``(N,)``."""
    half = int(math.ceil(4 * sigma))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    return np.convolve(np.pad(x, half, mode="edge"), k / k.sum(), mode="valid")


def _road_slope(vu: np.ndarray, speed: np.ndarray, min_speed: float, sigma: float) -> np.ndarray:
    """The road's slope as a pitch (climbing is nose up: negative), ``-atan(vu / v)``, held
    (linearly interpolated) where the car is slower than ``min_speed``. ``(N,)`` -> ``(N,)``."""
    moving = speed > min_speed
    if moving.sum() < 2:
        return np.zeros_like(vu)
    slope = -np.arctan2(vu, speed)
    idx = np.arange(len(vu))
    slope = np.interp(idx, idx[moving], slope[moving])
    return _gaussian_smooth(slope, sigma)


def _road_profile(stamps: np.ndarray, speed: np.ndarray, slope: np.ndarray, f_stamps: np.ndarray,
                  moving: np.ndarray, reach: float) -> RoadProfile:
    """The road's slope over the distance travelled (the speed's trapezoid), from the ``moving``
    records only: at a crawl or a stop the slope is held over time (``_road_slope``), which over
    the few centimetres driven would be a crease. Held for ``reach`` m past both ends."""
    s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(stamps))])
    knots = np.flatnonzero(moving)
    knots = knots[np.concatenate([[True], np.diff(s[knots]) > 1e-3])] if len(knots) else knots
    d, g = (s[knots], slope[knots]) if len(knots) >= 2 else (s[[0, -1]] + [0.0, 1.0], slope[[0, 0]])
    d = np.concatenate([[d[0] - reach - 20.0], d, [d[-1] + reach + 20.0]])
    g = np.concatenate([[g[0]], g, [g[-1]]])
    return RoadProfile(d, g, np.interp(f_stamps, stamps, s))


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _camera_clock(stamps: np.ndarray, window: int = 21) -> np.ndarray:
    """The camera's frame times behind jittered stamps: their running mean over ``window``
    records (a line's mean is the line: the camera's period, 0.1039 s on KITTI, and its slow
    changes are kept), lines fitted to the first and last ``window`` at the ends. ``(N,)`` -> ``(N,)``."""
    n = len(stamps)
    w = min(window, n) | 1
    half = w // 2
    out = stamps.copy()
    if n > w:
        out[half:n - half] = np.convolve(stamps, np.ones(w) / w, mode="valid")
    idx = np.arange(n)
    for sl in (slice(0, half), slice(n - half, n)):
        fit = slice(0, w) if sl.start == 0 else slice(n - w, n)
        coef = np.polyfit(idx[fit], stamps[fit], 1)
        out[sl] = np.polyval(coef, idx[sl])
    return out


def _interp(t: np.ndarray, values: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``(N, C)`` values at ``t`` to ``t_new``. -> ``(M, C)``."""
    return np.stack([np.interp(t_new, t, values[:, k]) for k in range(values.shape[1])], -1)


def _hermite(t: np.ndarray, values: np.ndarray, rates: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """The cubic through ``(N, C)`` values with their time derivatives ``rates``, at ``t_new``
    (clamped to ``t``'s span). -> ``(M, C)``."""
    t_new = np.clip(t_new, t[0], t[-1])
    i = np.clip(np.searchsorted(t, t_new, side="right") - 1, 0, len(t) - 2)
    h = (t[i + 1] - t[i])[:, None]
    u = ((t_new - t[i]) / h[:, 0])[:, None]
    h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
    return h00 * values[i] + h10 * h * rates[i] + h01 * values[i + 1] + h11 * h * rates[i + 1]


def drive_from_oxts(
    oxts: OxtsData,
    seed: int = 0,
    *,
    camera: CameraModel | None = None,
    render: bool | str = "lazy",
    render_options: RenderOptions | None = None,
    t0: float = 1000.0,
    slope_smoothing: float = 0.7,
    camber_smoothing: float = 2.0,
    lean_gradient: float = 0.0087,
    min_speed: float = 2.0,
    traffic: TrafficOptions | bool | None = None,
    vertical_curves: bool = False,
    bridge_interpolated: bool = True,
) -> SyntheticDrive:
    """A drive with the OXTS records' path and IMU and a rendered camera, one frame per record.

    Args:
        oxts: the records (``read_oxts``, ``OxtsData.slice`` for a part), at least 3.
        seed: the road texture and the image noise.
        camera: the rendered camera (default :func:`kitti_like_camera`).
        render: True = render every frame now; "lazy" = on access; False = no images.
        t0: stamp of the first record, seconds (the records keep their own intervals).
        slope_smoothing: the Gaussian (seconds) taking the body's heave out of the slope.
        camber_smoothing: the Gaussian (seconds) whose roll, less the lean, is the road's camber.
        lean_gradient: the body's roll out of a bend, rad per m/s^2 (0.0087: 0.5 deg, 5 deg per g).
        min_speed: below it (m/s) the slope is held: ``vu / v`` is noise at a crawl.
        traffic: other vehicles in the images (:mod:`.traffic`, as :func:`make_drive`'s), along the
            records' path; None/False = an empty road.
        vertical_curves: the images show the road ahead bent by the drive's slope further along
            (crests, sags); False = a plane. Not with ``traffic`` (its vehicles stand on the plane).
        bridge_interpolated: the IMU over KITTI's interpolated records bridged by the unit's attitude
            and velocity change across them (:func:`~bevo_ros.datasets.kitti.bridged_imu`), as ``bevo
            convert`` writes it by default; False = the line KITTI wrote. The truth is the same.

    Returns:
        a :class:`SyntheticDrive`: the IMU at the records' stamps, the frames on the camera's clock
        behind them (``frame_imu_index`` the nearest record); ``gyro_true`` and
        ``accel_true`` are the measured values and the biases zero: a real IMU's errors are unknown.
    """
    n = len(oxts)
    if n < 3:
        raise ValueError(f"need at least 3 OXTS records, got {n}")
    if render not in (True, False, "lazy"):
        raise ValueError(f"render must be True, False or 'lazy', got {render!r}")
    if vertical_curves and traffic:
        raise ValueError("vertical_curves and traffic cannot be combined: the vehicles stand on the road's plane")
    if not np.isfinite(oxts.data[:, :23]).all():
        raise ValueError("OXTS records hold non-finite values")
    stamps = float(t0) + (oxts.stamps_ns - oxts.stamps_ns[0]).astype(np.float64) * 1e-9
    dt = np.diff(stamps)
    if not (dt > 0).all():
        raise ValueError("OXTS stamps must increase")
    rate = 1.0 / float(np.median(dt))
    camera = camera if camera is not None else kitti_like_camera()

    xy = oxts_positions(oxts.field("lat"), oxts.field("lon"))
    vf, vl, vu = oxts.field("vf"), oxts.field("vl"), oxts.field("vu")
    speed = np.hypot(vf, vl)
    slope = _road_slope(vu, speed, min_speed, slope_smoothing * rate)
    pitch_rel = oxts.pitch - slope
    moving = speed > min_speed
    pitch_rel = pitch_rel - (pitch_rel[moving].mean() if moving.any() else pitch_rel.mean())
    lean = lean_gradient * speed * oxts.gyro[:, 2]
    camber = _gaussian_smooth(oxts.roll - lean, camber_smoothing * rate)
    pr_road = np.stack([pitch_rel, oxts.roll - camber], -1)
    tilt = np.stack([oxts.pitch - pitch_rel, camber], -1)

    # IMU-rate quantities, at the unit's own stamps.
    yaw_u = np.unwrap(oxts.yaw)
    r_grav = rotation_z(yaw_u) @ rotation_y(oxts.pitch) @ rotation_x(oxts.roll)
    vel = np.stack([oxts.field("ve"), oxts.field("vn"), vu], -1)
    gyro, accel = (bridged_imu(oxts, interpolated_oxts(oxts))[:2] if bridge_interpolated
                   else (oxts.gyro.copy(), oxts.accel.copy()))
    pr_grav = np.stack([oxts.pitch, oxts.roll], -1)
    imu_poses = np.concatenate([xy, _wrap(yaw_u)[:, None]], 1)

    # Frames on the camera's clock: KITTI's synced OXTS record is the unit's 100 Hz sample nearest
    # each camera frame, so its stamps (and the positions, which follow them to 0.5-0.7 cm on the
    # shared drives) jitter by +-5 ms against the camera's: 7 cm at 14 m/s. The camera is the
    # stamps' local mean; the frames' poses are interpolated to it (positions by the cubic
    # through the velocities, the rest linearly).
    f_stamps = _camera_clock(stamps)
    f_stamps = f_stamps[(f_stamps >= stamps[0]) & (f_stamps <= stamps[-1])]  # frames the IMU spans
    if len(f_stamps) < 2:
        raise ValueError("the records span fewer than 2 camera frames")
    f_xy = _hermite(stamps, xy, vel[:, :2], f_stamps)
    f_yaw = _hermite(stamps, yaw_u[:, None], oxts.gyro[:, 2:3], f_stamps)[:, 0]
    f_pr_road = _interp(stamps, pr_road, f_stamps)
    f_pr_grav = _interp(stamps, pr_grav, f_stamps)
    f_tilt = _interp(stamps, tilt, f_stamps)
    f_speed = np.interp(f_stamps, stamps, speed)
    poses = np.concatenate([f_xy, _wrap(f_yaw)[:, None]], 1)
    d = f_xy[1:] - f_xy[:-1]
    c, s = np.cos(f_yaw[:-1]), np.sin(f_yaw[:-1])
    rel = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], np.diff(f_yaw)], 1)
    nearest = np.clip(np.searchsorted(stamps, f_stamps), 1, n - 1)
    nearest = np.where(f_stamps - stamps[nearest - 1] < stamps[nearest] - f_stamps, nearest - 1, nearest)

    ground = RoadGround(seed, path=_lane_path(xy, yaw_u))
    options = render_options if render_options is not None else RenderOptions()
    t_base_cam = camera.T_base_cam.detach().cpu().double().numpy()[:3, 3]
    base_height = float(camera.mount_height) - (rotation_y(f_pr_road[:, 0]) @ rotation_x(f_pr_road[:, 1]) @ t_base_cam)[:, 2]
    drive = SyntheticDrive(
        camera=camera, ground=ground, seed=int(seed), frame_stamps=f_stamps, frame_imu_index=nearest, images=None,
        imu_stamps=stamps, gyro=gyro, accel=accel, gyro_true=gyro.copy(), accel_true=accel.copy(),
        gyro_bias=np.zeros_like(gyro), accel_bias=np.zeros_like(accel), poses_xy_yaw=poses,
        pitch_roll_road=f_pr_road, pitch_roll_gravity=f_pr_grav, road_slope_camber=f_tilt, relative_motion=rel,
        speed=f_speed, base_height=base_height, imu_pitch_roll_road=pr_road,
        imu_pitch_roll_gravity=pr_grav, imu_road_slope_camber=tilt, imu_rotation_gravity=r_grav,
        imu_velocity_gravity=vel, imu_poses_xy_yaw=imu_poses, render_options=options, image_noise=True,
    )
    if vertical_curves:
        drive.road_profile = _road_profile(stamps, speed, tilt[:, 0], f_stamps, moving, options.haze_end)
    traffic = as_traffic_options(traffic)
    if traffic is not None:
        drive.traffic = traffic_at_frames(traffic, stamps, xy, yaw_u, f_stamps, seed)
    if render == "lazy":
        drive.images = LazyImages(drive)
    elif render:
        drive.images = np.stack([render_frame(drive, i) for i in range(len(f_stamps))])
    return drive
